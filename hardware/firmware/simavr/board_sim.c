/*
 * board_sim.c - runs the walker board firmware on a simulated ATmega328P (simavr 1.6)
 * with the board's surroundings: a serial port, two quadrature encoders, two brakes.
 *
 *   board_sim [-s SPEED] [-t] [-r EDGE_RATE_HZ] [-i] -l LINK FIRMWARE.elf
 *
 *   -l LINK   the path of a symlink to the pseudo-terminal bridged to UART0 (what a
 *             serial driver opens, as it would /dev/ttyACM0); an old symlink there is
 *             replaced, anything else is an error
 *   -s SPEED  simulated time per wall-clock time (default 1.0; 0 = as fast as it
 *             can). When the host cannot keep up, the simulation runs slower and
 *             never catches up by more than 100 ms in a burst.
 *   -t        start with the `tx` events on
 *   -r HZ     the default maximum edge rate of `goto` (default 10000 edges/s/wheel)
 *   -i        an MPU-6050 IMU on the I2C bus (TWI) at address 0x68
 *
 * What it models:
 *   - UART0 <-> a pty (raw, no echo). Bytes from the host are handed to the AVR's
 *     UART one at a time, at the rate simavr's UART delivers them (simavr 1.6 counts
 *     a parity bit in every frame: 11 bits, 93.5 us per byte at UBRR0 16 with U2X0),
 *     so its 64-byte FIFO does not back up; bytes that arrive while the receiver is
 *     disabled (in reset, before the firmware enables it) are lost, as on the board.
 *     The harness holds the pty's slave open itself, so the port exists whether or
 *     not a driver has it open; `unplug` closes the pty (the driver's reads fail, the
 *     symlink disappears), `replug` makes a new one at the same path.
 *   - Encoders: PD2/PD4 (left A/B), PD3/PD5 (right A/B), driven with
 *     AVR_IOCTL_IOPORT_SET_EXTERNAL and the pins' IRQs, idle high. One step is one
 *     edge of the gray sequence AB = 00, 10, 11, 01 (forward: A leads B). A reset
 *     clears simavr's PINx registers, so the harness re-applies the line levels.
 *   - Brakes: OCR1A/OCR1B and the COM1A/COM1B bits are watched after every
 *     instruction; a change, once stable for 4 us (the firmware writes OCR and COM
 *     in consecutive instructions), is one `brake` event. The PB1/PB2 pin levels are
 *     timed to measure the duty over the last PWM period. While a compare output
 *     is disconnected the pin follows PORTB (simavr leaves it where the timer left
 *     it), and after a reset the pins are inputs pulled low (the driver's pull-down).
 *   - IMU (with -i): an InvenSense MPU-6050 at 0x68 on the AVR's TWI, as simavr's TWI
 *     master raises the transaction: a START with our address is acknowledged, WRITE
 *     bytes set the register pointer (the first) or a register (the pointer then
 *     advances), READ bytes return the register at the pointer (which advances), a
 *     STOP ends it. WHO_AM_I (0x75) reads 0x68; PWR_MGMT_1 (0x6B) starts at 0x40
 *     (asleep); written registers keep their values (an MCU reset does not reset the
 *     IMU). GYRO_ZOUT_H/L (0x47/0x48) give the `gyro` value (int16; 0 while asleep);
 *     reading 0x47 latches the pair. Without -i nobody answers on the bus.
 *
 * Control channel: one command per line on stdin; exactly one reply line per command
 * on stdout, in order: "OK [fields]" or "ERR <message>". Asynchronous events are
 * lines "E <sim_ns> <kind> [fields]" interleaved with the replies; sim_ns is the
 * simulated time in nanoseconds since power-on (cycles * 62.5 at 16 MHz). The
 * simulation runs in slices of 100 us of simulated time; commands take effect
 * between slices, at the simulated time the harness reads them.
 *
 *   time                        OK <sim_ns> <cycle>
 *   steps <L|R> <n> <period_us> OK; |n| edges on the wheel, one every period_us,
 *                               forward if n > 0; then  E <ns> done <L|R> <pos>
 *   goto <l> <r> [<rate_hz>]    OK; edges on each wheel, at most rate_hz per second,
 *                               until the wheel positions are l and r
 *   counts                      OK <pos_l> <pos_r> <target_l> <target_r>
 *   glitch <L|R>                OK <pos>; both lines of the wheel flip at once (the
 *                               board sees a quadrature error; the position moves
 *                               by two steps forward, which the board cannot count)
 *   brakes                      OK <sim_ns> <ocr1a> <ocr1b> <com1a> <com1b>
 *                                  <duty_pb1> <duty_pb2> <level_pb1> <level_pb2>
 *                                  <hz_pb1> <hz_pb2>
 *                               (duty: fraction of the last PWM period the pin was
 *                               high, or its constant level when it has not moved
 *                               for three periods; hz: 1 / that period, 0 then)
 *   pins                        OK <PIND> <encoder line levels> <PD2 level> <PD4 level>
 *   uart                        OK <ubrr> <u2x> <baud> <cycles_per_byte>
 *   tx <on|off>                 OK; the `tx` events
 *   reset                       OK <sim_ns>; an external reset (MCUSR EXTRF)
 *   unplug                      OK
 *   replug                      OK <pty slave path>
 *   alarm <sim_ns>              OK <id>; then  E <ns> alarm <id>  when the simulated
 *                               time reaches sim_ns (at once if it has passed)
 *   stats                       OK <sim_ns> <wall_ns> <rx_bytes> <tx_bytes>
 *                                  <rx_dropped> <tx_dropped>
 *                               (rx: host -> AVR bytes handed over / lost while the
 *                               receiver was off; tx: AVR -> pty bytes / lost while
 *                               unplugged or while nobody read the port)
 *   inject <hex>                OK <n>; n bytes to the host as if the AVR had sent them
 *                               (garbage on the line; mid-line if the AVR is sending)
 *   gyro <raw>                  OK; the IMU's z rate from now on, in LSB (-32768..32767)
 *   imu                         OK <pwr_mgmt_1> <smplrt_div> <config> <gyro_config>
 *                                  <gz_reads>  (the registers the firmware set; reads
 *                               of GYRO_ZOUT_H so far)
 *   quit                        OK, then exit (also on EOF of stdin and SIGTERM)
 *
 *   E <ns> ready <link> <slave>     once, before any reply
 *   E <ns> rx-nl <n>                the n-th '\n' from the host was handed to the
 *                                   AVR's UART (the firmware has it one byte time
 *                                   later)
 *   E <ns> brake <ocr1a> <ocr1b> <com1a> <com1b>
 *   E <ns> tx <line>                a line the AVR transmitted (with `tx on`; not
 *                                   empty lines; a line a reset cut short is
 *                                   reported at the reset)
 *   E <ns> reset <mcusr>            the MCU was reset (8: watchdog, 2: external)
 *   E <ns> done <L|R> <pos>         a `steps` finished
 *   E <ns> plug <0|1> <slave|->     the pty was closed / made
 *   E <ns> alarm <id>               an `alarm` went off
 *   E <ns> halt <state>             the MCU stopped (crashed, or slept with
 *                                   interrupts off); `reset` restarts it
 *
 * Wheel positions are the edges the harness generated since it started (the
 * "true" encoder counts); the board's counts equal them until the board resets,
 * after which the board counts from 0 again.
 */

#define _GNU_SOURCE
#include <ctype.h>
#include <errno.h>
#include <fcntl.h>
#include <getopt.h>
#include <inttypes.h>
#include <poll.h>
#include <pty.h>
#include <signal.h>
#include <stdarg.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <sys/stat.h>
#include <termios.h>
#include <time.h>
#include <unistd.h>

#include "avr_ioport.h"
#include "avr_twi.h"
#include "avr_uart.h"
#include "sim_avr.h"
#include "sim_elf.h"
#include "sim_regbit.h"

/* ATmega328P data-space addresses and bits the harness reads */
#define R_PINB 0x23
#define R_DDRB 0x24
#define R_PORTB 0x25
#define R_PIND 0x29
#define R_TCCR1A 0x80
#define R_OCR1AL 0x88
#define R_OCR1AH 0x89
#define R_OCR1BL 0x8A
#define R_OCR1BH 0x8B
#define R_UCSR0A 0xC0
#define R_UCSR0B 0xC1
#define R_UCSR0C 0xC2
#define R_UBRR0L 0xC4
#define R_UBRR0H 0xC5
#define BIT_U2X0 1
#define BIT_RXEN0 4
#define BIT_USBS0 3

#define F_CPU 16000000u
#define ENC_MASK 0x3C          /* PD2..PD5 */
#define PWM_PERIOD 16384u      /* Timer1 fast PWM 8-bit, prescaler 64 */
#define BRAKE_SETTLE 64u       /* cycles a brake register change must be stable */
#define SLICE_CYCLES 1600u     /* 100 us between looks at the outside world */
#define MAX_BEHIND_NS 100000000ull
#define RING 65536u

static avr_t *avr;
static volatile sig_atomic_t quit_signal;
static int quitting;
static double speed = 1.0;
static int tx_events;
static double default_edge_rate = 10000.0;
static const char *link_path;

/* ------------------------------------------------------------------ output -- */

static int out_dirty;

static uint64_t cycles_to_ns(uint64_t c)
{
    uint64_t f = avr->frequency;
    return c / f * 1000000000ull + c % f * 1000000000ull / f;
}

static void out(const char *fmt, ...) __attribute__((format(printf, 1, 2)));
static void out(const char *fmt, ...)
{
    va_list ap;
    va_start(ap, fmt);
    vfprintf(stdout, fmt, ap);
    va_end(ap);
    out_dirty = 1;
}

static void event(uint64_t cycle, const char *fmt, ...) __attribute__((format(printf, 2, 3)));
static void event(uint64_t cycle, const char *fmt, ...)
{
    va_list ap;
    fprintf(stdout, "E %" PRIu64 " ", cycles_to_ns(cycle));
    va_start(ap, fmt);
    vfprintf(stdout, fmt, ap);
    va_end(ap);
    fputc('\n', stdout);
    out_dirty = 1;
}

static void logger(avr_t *a, const int level, const char *fmt, va_list ap)
{
    (void)a;
    if (level <= LOG_ERROR) {
        fputs("simavr: ", stderr);
        vfprintf(stderr, fmt, ap);
    }
}

/* ------------------------------------------------------------ byte rings -- */

typedef struct {
    uint8_t buf[RING];
    uint32_t head, tail; /* free-running; used = head - tail */
} ring_t;

static uint32_t ring_used(const ring_t *r) { return r->head - r->tail; }
static uint32_t ring_free(const ring_t *r) { return RING - ring_used(r); }
static void ring_put(ring_t *r, uint8_t c) { r->buf[r->head++ % RING] = c; }
static uint8_t ring_get(ring_t *r) { return r->buf[r->tail++ % RING]; }

static ring_t host_rx; /* pty -> AVR */
static ring_t host_tx; /* AVR -> pty */
static uint64_t rx_bytes, tx_bytes, rx_dropped, tx_dropped;

/* ---------------------------------------------------------------- the pty -- */

static int pty_master = -1, pty_slave = -1;
static char pty_name[128];

static int pty_open(void)
{
    int m, s;
    if (openpty(&m, &s, pty_name, NULL, NULL) < 0)
        return -1;
    struct termios t;
    if (tcgetattr(s, &t) == 0) {
        cfmakeraw(&t);
        cfsetispeed(&t, B115200);
        cfsetospeed(&t, B115200);
        tcsetattr(s, TCSANOW, &t);
    }
    fcntl(m, F_SETFL, fcntl(m, F_GETFL) | O_NONBLOCK);
    fcntl(m, F_SETFD, FD_CLOEXEC);
    fcntl(s, F_SETFD, FD_CLOEXEC);
    /* point the link at the slave atomically; never replace anything but a symlink */
    struct stat st;
    if (lstat(link_path, &st) == 0 && !S_ISLNK(st.st_mode)) {
        close(m);
        close(s);
        errno = EEXIST;
        return -1;
    }
    char tmp[4096];
    snprintf(tmp, sizeof tmp, "%s.tmp%d", link_path, (int)getpid());
    unlink(tmp);
    if (symlink(pty_name, tmp) < 0 || rename(tmp, link_path) < 0) {
        unlink(tmp);
        close(m);
        close(s);
        return -1;
    }
    pty_master = m;
    pty_slave = s;
    return 0;
}

static void pty_close(void)
{
    if (pty_master < 0)
        return;
    struct stat st;
    if (lstat(link_path, &st) == 0 && S_ISLNK(st.st_mode))
        unlink(link_path);
    close(pty_master);
    close(pty_slave);
    pty_master = pty_slave = -1;
    host_rx.tail = host_rx.head; /* bytes of a vanished port */
    host_tx.tail = host_tx.head;
}

static void pty_flush(void)
{
    while (pty_master >= 0 && ring_used(&host_tx)) {
        uint32_t t = host_tx.tail % RING;
        uint32_t n = ring_used(&host_tx);
        if (n > RING - t)
            n = RING - t;
        ssize_t w = write(pty_master, host_tx.buf + t, n);
        if (w <= 0) {
            /* the slave's queue is full (nobody reads the port): like the Uno's USB
             * bridge, drop what does not fit instead of delivering it stale later */
            tx_dropped += ring_used(&host_tx);
            host_tx.tail = host_tx.head;
            return;
        }
        host_tx.tail += (uint32_t)w;
    }
}

static void pty_read(void)
{
    uint8_t buf[4096];
    uint32_t room = ring_free(&host_rx);
    if (room > sizeof buf)
        room = sizeof buf;
    if (!room)
        return;
    ssize_t n = read(pty_master, buf, room);
    for (ssize_t i = 0; i < n; i++)
        ring_put(&host_rx, buf[i]);
}

/* ---------------------------------------------------------------- UART0 -- */

static avr_irq_t *uart_in;
static int uart_xoff;
static int feeder_active;
static uint64_t newlines;
static char tx_line[256];
static unsigned tx_len;

static uint32_t uart_cycles_per_byte(void)
{
    uint32_t ubrr = avr->data[R_UBRR0L] | (uint32_t)(avr->data[R_UBRR0H] & 0x0F) << 8;
    uint32_t per_bit = (ubrr + 1) * 8 * ((avr->data[R_UCSR0A] >> BIT_U2X0) & 1 ? 1 : 2);
    uint32_t stop = (avr->data[R_UCSR0C] >> BIT_USBS0) & 1 ? 2 : 1;
    return per_bit * (1 + 8 + 1 + stop); /* simavr's frame: start, 8 data, parity, stop */
}

static avr_cycle_count_t feed_timer(avr_t *a, avr_cycle_count_t when, void *param)
{
    (void)param;
    if (!ring_used(&host_rx)) {
        feeder_active = 0;
        return 0;
    }
    if (!((a->data[R_UCSR0B] >> BIT_RXEN0) & 1)) { /* receiver off: the bytes are lost */
        rx_dropped += ring_used(&host_rx);
        host_rx.tail = host_rx.head;
        feeder_active = 0;
        return 0;
    }
    if (!uart_xoff) {
        uint8_t c = ring_get(&host_rx);
        rx_bytes++;
        avr_raise_irq(uart_in, c);
        if (c == '\n')
            event(when, "rx-nl %" PRIu64, ++newlines);
    }
    return when + uart_cycles_per_byte();
}

static void feeder_start(void)
{
    if (!feeder_active && ring_used(&host_rx)) {
        feeder_active = 1;
        avr_cycle_timer_register(avr, 1, feed_timer, NULL);
    }
}

/* The line the AVR sent so far as a `tx` event (empty lines are not reported). */
static void tx_flush_line(void)
{
    if (tx_len) {
        tx_line[tx_len] = 0;
        event(avr->cycle, "tx %s", tx_line);
    }
    tx_len = 0;
}

static void uart_out_notify(avr_irq_t *irq, uint32_t value, void *param)
{
    (void)irq;
    (void)param;
    uint8_t c = (uint8_t)value;
    if (pty_master >= 0 && ring_free(&host_tx)) {
        ring_put(&host_tx, c);
        tx_bytes++;
    } else {
        tx_dropped++;
    }
    if (!tx_events)
        return;
    if (c == '\n' || tx_len == sizeof tx_line - 1) {
        tx_flush_line();
        if (c == '\n')
            return;
    }
    if (c != '\r')
        tx_line[tx_len++] = (c >= 0x20 && c < 0x7F) ? (char)c : '?';
}

static void uart_xoff_notify(avr_irq_t *irq, uint32_t value, void *param)
{
    (void)irq;
    (void)param;
    uart_xoff = value != 0;
}

/* ------------------------------------------------------------- encoders -- */

typedef struct {
    char name;
    int pin_a, pin_b;       /* PORTD bits */
    int64_t pos, target;    /* edges generated / to generate */
    uint64_t period;        /* cycles between edges */
    int active, notify;
    unsigned phase;         /* gray sequence index: AB = 00, 10, 11, 01 */
} wheel_t;

static wheel_t wheels[2] = {
    {.name = 'L', .pin_a = 2, .pin_b = 4, .phase = 2},
    {.name = 'R', .pin_a = 3, .pin_b = 5, .phase = 2},
};
static uint8_t enc_levels = ENC_MASK; /* idle high */
static avr_irq_t *portd_irq[8];

static void enc_set(int bit, int level)
{
    if (level)
        enc_levels |= (uint8_t)(1 << bit);
    else
        enc_levels &= (uint8_t)~(1 << bit);
    avr_ioport_external_t ext = {.name = 'D', .mask = ENC_MASK, .value = enc_levels};
    avr_ioctl(avr, AVR_IOCTL_IOPORT_SET_EXTERNAL('D'), &ext);
    avr_raise_irq(portd_irq[bit], (uint32_t)level);
}

static void wheel_levels(unsigned phase, int *a, int *b)
{
    static const uint8_t ab[4] = {0x0, 0x2, 0x3, 0x1}; /* A << 1 | B */
    *a = (ab[phase & 3] >> 1) & 1;
    *b = ab[phase & 3] & 1;
}

/* Moves a wheel to a new phase, flipping the lines that change. */
static void wheel_phase(wheel_t *w, unsigned phase)
{
    int a0, b0, a1, b1;
    wheel_levels(w->phase, &a0, &b0);
    wheel_levels(phase, &a1, &b1);
    w->phase = phase & 3;
    if (a1 != a0)
        enc_set(w->pin_a, a1);
    if (b1 != b0)
        enc_set(w->pin_b, b1);
}

static avr_cycle_count_t wheel_timer(avr_t *a, avr_cycle_count_t when, void *param)
{
    (void)a;
    wheel_t *w = param;
    if (w->pos != w->target) {
        int dir = w->target > w->pos ? 1 : -1;
        w->pos += dir;
        wheel_phase(w, w->phase + (unsigned)(dir > 0 ? 1 : 3));
    }
    if (w->pos == w->target) {
        w->active = 0;
        if (w->notify) {
            w->notify = 0;
            event(when, "done %c %" PRId64, w->name, w->pos);
        }
        return 0;
    }
    return when + w->period;
}

static void wheel_start(wheel_t *w)
{
    if (!w->active && w->pos != w->target) {
        w->active = 1;
        avr_cycle_timer_register(avr, w->period, wheel_timer, w);
    } else if (w->notify && w->pos == w->target) {
        w->notify = 0;
        event(avr->cycle, "done %c %" PRId64, w->name, w->pos);
    }
}

/* --------------------------------------------------------------- brakes -- */

typedef struct {
    avr_irq_t *irq;
    uint64_t rise, fall, last_edge;
    uint64_t high, period;
    int have_rise, valid;
} pin_meter_t;

static pin_meter_t meters[2];

static struct {
    uint8_t tccr, com_a, com_b;
    uint16_t ocr_a, ocr_b;
    int pending;
    uint64_t changed;
} brake;

static void pin_notify(avr_irq_t *irq, uint32_t value, void *param)
{
    (void)irq;
    pin_meter_t *m = param;
    uint64_t now = avr->cycle;
    if (value & 1) {
        if (m->have_rise && m->fall > m->rise) {
            m->period = now - m->rise;
            m->high = m->fall - m->rise;
            m->valid = 1;
        }
        m->rise = now;
        m->have_rise = 1;
    } else {
        m->fall = now;
    }
    m->last_edge = now;
}

static int pin_still(const pin_meter_t *m)
{
    return !m->valid || avr->cycle - m->last_edge > 3 * PWM_PERIOD;
}

static double pin_duty(const pin_meter_t *m)
{
    if (pin_still(m))
        return (m->irq->value & 1) ? 1.0 : 0.0;
    return (double)m->high / (double)m->period;
}

static double pin_hz(const pin_meter_t *m)
{
    return pin_still(m) ? 0.0 : (double)avr->frequency / (double)m->period;
}

/* A disconnected compare output leaves the pin to PORTB (or to the pull-down
 * when the pin is an input), which simavr does not do by itself. */
static void pin_follow_port(int i)
{
    uint8_t bit = (uint8_t)(1 << (i + 1)); /* PB1, PB2 */
    int level = (avr->data[R_DDRB] & bit) && (avr->data[R_PORTB] & bit);
    avr_raise_irq(meters[i].irq, (uint32_t)level);
}

static inline void brake_check(void)
{
    uint8_t tccr = avr->data[R_TCCR1A] & 0xF0;
    uint16_t a = avr->data[R_OCR1AL] | (uint16_t)avr->data[R_OCR1AH] << 8;
    uint16_t b = avr->data[R_OCR1BL] | (uint16_t)avr->data[R_OCR1BH] << 8;
    if (tccr != brake.tccr || a != brake.ocr_a || b != brake.ocr_b) {
        brake.tccr = tccr;
        brake.ocr_a = a;
        brake.ocr_b = b;
        brake.pending = 1;
        brake.changed = avr->cycle;
        if (!(tccr >> 6))
            pin_follow_port(0);
        if (!((tccr >> 4) & 3))
            pin_follow_port(1);
    } else if (brake.pending && avr->cycle - brake.changed >= BRAKE_SETTLE) {
        brake.pending = 0;
        event(brake.changed, "brake %u %u %u %u", brake.ocr_a, brake.ocr_b, brake.tccr >> 6,
              (brake.tccr >> 4) & 3);
    }
}

/* --------------------------------------------------------------- alarms -- */

#define MAX_ALARMS 16

typedef struct {
    int used;
    unsigned id;
    uint64_t cycle;
} alarm_t;

static alarm_t alarms[MAX_ALARMS];
static unsigned next_alarm_id = 1;

static avr_cycle_count_t alarm_timer(avr_t *a, avr_cycle_count_t when, void *param)
{
    (void)a;
    alarm_t *al = param;
    al->used = 0;
    event(when, "alarm %u", al->id);
    return 0;
}

static void alarm_arm(alarm_t *al)
{
    uint64_t now = avr->cycle;
    avr_cycle_timer_register(avr, al->cycle > now ? al->cycle - now : 1, alarm_timer, al);
}

/* ------------------------------------------------------------------ IMU -- */

#define IMU_ADDR 0x68
#define MPU_GYRO_ZOUT_H 0x47
#define MPU_GYRO_ZOUT_L 0x48
#define MPU_SMPLRT_DIV 0x19
#define MPU_CONFIG 0x1A
#define MPU_GYRO_CONFIG 0x1B
#define MPU_PWR_MGMT_1 0x6B
#define MPU_WHO_AM_I 0x75
#define MPU_SLEEP 0x40

static struct {
    int present;
    avr_irq_t *to_avr;
    uint8_t reg[128];
    uint8_t ptr, selected, addressed; /* addressed: the register pointer was written */
    int16_t gz;
    uint8_t gz_low; /* latched with the high byte */
    uint64_t gz_reads;
} imu;

static uint8_t imu_load(uint8_t r)
{
    int awake = !(imu.reg[MPU_PWR_MGMT_1] & MPU_SLEEP);
    uint16_t gz = awake ? (uint16_t)imu.gz : 0;
    if (r == MPU_GYRO_ZOUT_H) {
        imu.gz_low = (uint8_t)gz;
        imu.gz_reads++;
        return (uint8_t)(gz >> 8);
    }
    return r == MPU_GYRO_ZOUT_L ? imu.gz_low : imu.reg[r & 0x7F];
}

static void imu_ack(uint8_t addr)
{
    avr_raise_irq(imu.to_avr, avr_twi_irq_msg(TWI_COND_ACK, addr, 1));
}

/* A TWI condition or byte the AVR (the bus master) put on the bus. */
static void twi_notify(avr_irq_t *irq, uint32_t value, void *param)
{
    (void)irq;
    (void)param;
    avr_twi_msg_irq_t v;
    v.u.v = value;
    uint8_t msg = v.u.twi.msg, addr = v.u.twi.addr, data = v.u.twi.data;
    if (msg & TWI_COND_STOP)
        imu.selected = 0;
    if (msg & TWI_COND_START) {
        imu.selected = (addr >> 1) == IMU_ADDR;
        imu.addressed = 0;
        if (imu.selected)
            imu_ack(addr);
        return;
    }
    if (!imu.selected)
        return;
    if (msg & TWI_COND_WRITE) {
        imu_ack(addr);
        if (!imu.addressed) {
            imu.ptr = data & 0x7F;
            imu.addressed = 1;
        } else if (imu.ptr != MPU_WHO_AM_I) {
            imu.reg[imu.ptr] = data;
            imu.ptr = (imu.ptr + 1) & 0x7F;
        }
    } else if (msg & TWI_COND_READ) {
        uint8_t b = imu_load(imu.ptr);
        imu.ptr = (imu.ptr + 1) & 0x7F;
        avr_raise_irq(imu.to_avr, avr_twi_irq_msg(TWI_COND_READ, addr, b));
    }
}

static void imu_attach(void)
{
    imu.present = 1;
    imu.reg[MPU_WHO_AM_I] = IMU_ADDR;
    imu.reg[MPU_PWR_MGMT_1] = MPU_SLEEP;
    imu.to_avr = avr_io_getirq(avr, AVR_IOCTL_TWI_GETIRQ(0), TWI_IRQ_INPUT);
    avr_irq_register_notify(avr_io_getirq(avr, AVR_IOCTL_TWI_GETIRQ(0), TWI_IRQ_OUTPUT),
                            twi_notify, NULL);
}

/* ---------------------------------------------------------------- reset -- */

static void (*core_reset)(avr_t *);
static int reset_seen;

/* Called inside every avr_reset() (the command's or the watchdog's), after the I/O
 * registers and the cycle timers were cleared. */
static void on_reset(avr_t *a)
{
    if (core_reset)
        core_reset(a);
    a->data[R_PIND] = (uint8_t)((a->data[R_PIND] & ~ENC_MASK) | enc_levels);
    for (int i = 0; i < 2; i++) {
        pin_follow_port(i);
        wheels[i].active = 0;
        wheel_start(&wheels[i]);
    }
    for (int i = 0; i < MAX_ALARMS; i++)
        if (alarms[i].used)
            alarm_arm(&alarms[i]);
    uart_xoff = 0;
    feeder_active = 0;
    feeder_start();
    if (tx_events)
        tx_flush_line(); /* a line the reset cut short */
    reset_seen = 1;
}

static uint8_t mcusr(void) { return avr->data[avr->reset_flags.porf.reg]; }

/* -------------------------------------------------------------- pacing -- */

static uint64_t wall_ns(void)
{
    struct timespec t;
    clock_gettime(CLOCK_MONOTONIC, &t);
    return (uint64_t)t.tv_sec * 1000000000ull + (uint64_t)t.tv_nsec;
}

static uint64_t wall_start, wall_base, sim_base_ns;

static void sleep_nothing(avr_t *a, avr_cycle_count_t how_long)
{
    (void)a;
    (void)how_long; /* the main loop paces */
}

/* ------------------------------------------------------------- commands -- */

static int wheel_index(const char *s)
{
    if (!strcmp(s, "L") || !strcmp(s, "l"))
        return 0;
    if (!strcmp(s, "R") || !strcmp(s, "r"))
        return 1;
    return -1;
}

/* "inject <hex>": bytes to the host as if the AVR had sent them (garbage on the line). */
static int inject(const char *hex)
{
    size_t k = 0;
    unsigned v;
    while (hex[0] && hex[1] && isxdigit((unsigned char)hex[0]) &&
           isxdigit((unsigned char)hex[1]) && sscanf(hex, "%2x", &v) == 1) {
        if (pty_master >= 0 && ring_free(&host_tx))
            ring_put(&host_tx, (uint8_t)v);
        hex += 2;
        k++;
    }
    while (*hex == ' ' || *hex == '\r' || *hex == '\n')
        hex++;
    return *hex ? -1 : (int)k;
}

static void command(char *line)
{
    if (!strncmp(line, "inject ", 7)) {
        int k = inject(line + 7);
        if (k < 0)
            out("ERR usage: inject HEX (pairs of hexadecimal digits)\n");
        else
            out("OK %d\n", k);
        return;
    }
    char cmd[16] = "", a1[32] = "", a2[32] = "", a3[32] = "", extra[2] = "";
    int n = sscanf(line, "%15s %31s %31s %31s %1s", cmd, a1, a2, a3, extra);
    if (n <= 0)
        return; /* blank line: no reply */
    char *end;
    if (!strcmp(cmd, "time") && n == 1) {
        out("OK %" PRIu64 " %" PRIu64 "\n", cycles_to_ns(avr->cycle), (uint64_t)avr->cycle);
    } else if (!strcmp(cmd, "steps") && n == 4) {
        int w = wheel_index(a1);
        long long steps = strtoll(a2, &end, 10);
        double period_us = strtod(a3, NULL);
        if (w < 0 || *end || period_us < 1.0 || period_us > 1e7) {
            out("ERR usage: steps L|R N PERIOD_US (PERIOD_US in [1, 1e7])\n");
            return;
        }
        wheel_t *wh = &wheels[w];
        wh->target += steps;
        wh->period = (uint64_t)(period_us * F_CPU / 1e6 + 0.5);
        wh->notify = 1;
        wheel_start(wh);
        out("OK\n");
    } else if (!strcmp(cmd, "goto") && (n == 3 || n == 4)) {
        char *end2;
        long long l = strtoll(a1, &end, 10), r = strtoll(a2, &end2, 10);
        double rate = n == 4 ? strtod(a3, NULL) : default_edge_rate;
        if (*end || *end2 || rate < 0.1 || rate > 1e6) {
            out("ERR usage: goto L R [RATE_HZ] (RATE_HZ in [0.1, 1e6])\n");
            return;
        }
        uint64_t period = (uint64_t)(F_CPU / rate + 0.5);
        wheels[0].target = l;
        wheels[1].target = r;
        for (int i = 0; i < 2; i++) {
            wheels[i].period = period;
            wheel_start(&wheels[i]);
        }
        out("OK\n");
    } else if (!strcmp(cmd, "counts") && n == 1) {
        out("OK %" PRId64 " %" PRId64 " %" PRId64 " %" PRId64 "\n", wheels[0].pos, wheels[1].pos,
            wheels[0].target, wheels[1].target);
    } else if (!strcmp(cmd, "glitch") && n == 2 && wheel_index(a1) >= 0) {
        wheel_t *wh = &wheels[wheel_index(a1)];
        wh->pos += 2;
        wh->target += 2;
        wheel_phase(wh, wh->phase + 2);
        out("OK %" PRId64 "\n", wh->pos);
    } else if (!strcmp(cmd, "pins") && n == 1) {
        out("OK %u %u %u %u\n", avr->data[R_PIND], enc_levels, portd_irq[2]->value,
            portd_irq[4]->value);
    } else if (!strcmp(cmd, "brakes") && n == 1) {
        out("OK %" PRIu64 " %u %u %u %u %.4f %.4f %u %u %.2f %.2f\n", cycles_to_ns(avr->cycle),
            avr->data[R_OCR1AL] | avr->data[R_OCR1AH] << 8,
            avr->data[R_OCR1BL] | avr->data[R_OCR1BH] << 8, avr->data[R_TCCR1A] >> 6,
            (avr->data[R_TCCR1A] >> 4) & 3, pin_duty(&meters[0]), pin_duty(&meters[1]),
            meters[0].irq->value & 1, meters[1].irq->value & 1, pin_hz(&meters[0]),
            pin_hz(&meters[1]));
    } else if (!strcmp(cmd, "uart") && n == 1) {
        uint32_t ubrr = avr->data[R_UBRR0L] | (uint32_t)(avr->data[R_UBRR0H] & 0x0F) << 8;
        int u2x = (avr->data[R_UCSR0A] >> BIT_U2X0) & 1;
        double baud = (double)avr->frequency / ((ubrr + 1) * (u2x ? 8.0 : 16.0));
        out("OK %u %d %.1f %u\n", ubrr, u2x, baud, uart_cycles_per_byte());
    } else if (!strcmp(cmd, "tx") && n == 2 && (!strcmp(a1, "on") || !strcmp(a1, "off"))) {
        tx_events = !strcmp(a1, "on");
        tx_len = 0;
        out("OK\n");
    } else if (!strcmp(cmd, "reset") && n == 1) {
        avr_reset(avr);
        avr_regbit_set(avr, avr->reset_flags.extrf);
        reset_seen = 0;
        event(avr->cycle, "reset %u", mcusr());
        out("OK %" PRIu64 "\n", cycles_to_ns(avr->cycle));
    } else if (!strcmp(cmd, "unplug") && n == 1) {
        if (pty_master >= 0) {
            pty_close();
            event(avr->cycle, "plug 0 -");
        }
        out("OK\n");
    } else if (!strcmp(cmd, "replug") && n == 1) {
        if (pty_master < 0) {
            if (pty_open() < 0) {
                out("ERR cannot make the pty at %s: %s\n", link_path, strerror(errno));
                return;
            }
            event(avr->cycle, "plug 1 %s", pty_name);
        }
        out("OK %s\n", pty_name);
    } else if (!strcmp(cmd, "alarm") && n == 2) {
        unsigned long long ns = strtoull(a1, &end, 10);
        alarm_t *al = NULL;
        for (int i = 0; i < MAX_ALARMS && !al; i++)
            if (!alarms[i].used)
                al = &alarms[i];
        if (*end || !al) {
            out("ERR usage: alarm SIM_NS (at most %d pending)\n", MAX_ALARMS);
            return;
        }
        al->used = 1;
        al->id = next_alarm_id++;
        al->cycle = ns / 1000000000ull * avr->frequency +
                    (ns % 1000000000ull * avr->frequency + 999999999ull) / 1000000000ull;
        alarm_arm(al);
        out("OK %u\n", al->id);
    } else if (!strcmp(cmd, "stats") && n == 1) {
        out("OK %" PRIu64 " %" PRIu64 " %" PRIu64 " %" PRIu64 " %" PRIu64 " %" PRIu64 "\n",
            cycles_to_ns(avr->cycle), wall_ns() - wall_start, rx_bytes, tx_bytes, rx_dropped,
            tx_dropped);
    } else if (!strcmp(cmd, "gyro") && n == 2) {
        long raw = strtol(a1, &end, 10);
        if (!imu.present) {
            out("ERR no IMU: start board_sim with -i\n");
            return;
        }
        if (*end || raw < -32768 || raw > 32767) {
            out("ERR usage: gyro RAW (-32768..32767)\n");
            return;
        }
        imu.gz = (int16_t)raw;
        out("OK\n");
    } else if (!strcmp(cmd, "imu") && n == 1) {
        if (!imu.present) {
            out("ERR no IMU: start board_sim with -i\n");
            return;
        }
        out("OK %u %u %u %u %" PRIu64 "\n", imu.reg[MPU_PWR_MGMT_1], imu.reg[MPU_SMPLRT_DIV],
            imu.reg[MPU_CONFIG], imu.reg[MPU_GYRO_CONFIG], imu.gz_reads);
    } else if (!strcmp(cmd, "quit") && n == 1) {
        out("OK\n");
        quitting = 1;
    } else {
        out("ERR unknown command or wrong arguments: %.60s\n", line);
    }
}

static char cmd_buf[4096];
static size_t cmd_len;

/* Returns 0 on EOF. */
static int read_commands(void)
{
    ssize_t n = read(STDIN_FILENO, cmd_buf + cmd_len, sizeof cmd_buf - 1 - cmd_len);
    if (n == 0)
        return 0;
    if (n < 0)
        return errno == EAGAIN || errno == EINTR;
    cmd_len += (size_t)n;
    char *start = cmd_buf, *nl;
    while ((nl = memchr(start, '\n', cmd_len - (size_t)(start - cmd_buf)))) {
        *nl = 0;
        command(start);
        start = nl + 1;
    }
    cmd_len -= (size_t)(start - cmd_buf);
    memmove(cmd_buf, start, cmd_len);
    if (cmd_len == sizeof cmd_buf - 1) { /* a line too long for a command */
        out("ERR command line too long\n");
        cmd_len = 0;
    }
    return 1;
}

/* ----------------------------------------------------------------- main -- */

static void on_signal(int sig)
{
    (void)sig;
    quit_signal = 1;
}

static void usage(void)
{
    fprintf(stderr,
            "usage: board_sim [-s SPEED] [-t] [-r EDGE_RATE_HZ] [-i] -l LINK FIRMWARE.elf\n");
    exit(2);
}

int main(int argc, char **argv)
{
    int opt, with_imu = 0;
    while ((opt = getopt(argc, argv, "s:tr:il:")) != -1) {
        switch (opt) {
        case 's':
            speed = strtod(optarg, NULL);
            break;
        case 't':
            tx_events = 1;
            break;
        case 'r':
            default_edge_rate = strtod(optarg, NULL);
            break;
        case 'l':
            link_path = optarg;
            break;
        case 'i':
            with_imu = 1;
            break;
        default:
            usage();
        }
    }
    if (!link_path || optind != argc - 1 || speed < 0 || default_edge_rate < 0.1)
        usage();
    const char *elf = argv[optind];

    signal(SIGPIPE, SIG_IGN);
    struct sigaction sa = {.sa_handler = on_signal};
    sigaction(SIGTERM, &sa, NULL);
    sigaction(SIGINT, &sa, NULL);
    avr_global_logger_set(logger);

    elf_firmware_t fw;
    memset(&fw, 0, sizeof fw);
    if (elf_read_firmware(elf, &fw) != 0 || !fw.flashsize) {
        fprintf(stderr, "board_sim: cannot read the firmware %s\n", elf);
        return 1;
    }
    if (!fw.frequency)
        fw.frequency = F_CPU;
    avr = avr_make_mcu_by_name(fw.mmcu[0] ? fw.mmcu : "atmega328p");
    if (!avr) {
        fprintf(stderr, "board_sim: simavr has no ATmega328P\n");
        return 1;
    }
    avr_init(avr);
    avr_load_firmware(avr, &fw);
    if (avr->frequency != F_CPU) {
        fprintf(stderr, "board_sim: the firmware asks for %u Hz, the board runs at %u Hz\n",
                avr->frequency, F_CPU);
        return 1;
    }
    avr->sleep = sleep_nothing;
    core_reset = avr->reset;
    avr->reset = on_reset;

    uint32_t uart_flags = 0; /* no stdio echo of the UART, no usleep on polling */
    avr_ioctl(avr, AVR_IOCTL_UART_SET_FLAGS('0'), &uart_flags);
    uart_in = avr_io_getirq(avr, AVR_IOCTL_UART_GETIRQ('0'), UART_IRQ_INPUT);
    avr_irq_register_notify(avr_io_getirq(avr, AVR_IOCTL_UART_GETIRQ('0'), UART_IRQ_OUTPUT),
                            uart_out_notify, NULL);
    avr_irq_register_notify(avr_io_getirq(avr, AVR_IOCTL_UART_GETIRQ('0'), UART_IRQ_OUT_XOFF),
                            uart_xoff_notify, NULL);

    for (int i = 0; i < 8; i++)
        portd_irq[i] = avr_io_getirq(avr, AVR_IOCTL_IOPORT_GETIRQ('D'), i);
    for (int bit = 2; bit <= 5; bit++)
        enc_set(bit, 1); /* idle high, before the firmware runs (see LIVE.md) */
    for (int i = 0; i < 2; i++) {
        meters[i].irq = avr_io_getirq(avr, AVR_IOCTL_IOPORT_GETIRQ('B'), i + 1);
        avr_irq_register_notify(meters[i].irq, pin_notify, &meters[i]);
    }
    if (with_imu)
        imu_attach();

    if (pty_open() < 0) {
        fprintf(stderr, "board_sim: cannot make the pty at %s: %s\n", link_path, strerror(errno));
        return 1;
    }
    fcntl(STDIN_FILENO, F_SETFL, fcntl(STDIN_FILENO, F_GETFL) | O_NONBLOCK);
    event(avr->cycle, "ready %s %s", link_path, pty_name);
    fflush(stdout);

    wall_start = wall_base = wall_ns();
    sim_base_ns = cycles_to_ns(avr->cycle);
    int halted = 0;

    while (!quitting && !quit_signal) {
        if (!halted) {
            avr_cycle_count_t end = avr->cycle + SLICE_CYCLES;
            while (avr->cycle < end) {
                int state = avr_run(avr);
                brake_check();
                if (reset_seen) {
                    reset_seen = 0;
                    event(avr->cycle, "reset %u", mcusr());
                }
                if (state == cpu_Done || state == cpu_Crashed) {
                    event(avr->cycle, "halt %d", state);
                    halted = 1;
                    break;
                }
            }
        }
        pty_flush();

        /* pacing: how long until the wall clock reaches the simulated time */
        int64_t wait_ns = 0;
        uint64_t now = wall_ns();
        if (halted) {
            wait_ns = 10000000;
        } else if (speed > 0) {
            uint64_t sim_ns = cycles_to_ns(avr->cycle);
            uint64_t due = wall_base + (uint64_t)((double)(sim_ns - sim_base_ns) / speed);
            if (due > now)
                wait_ns = (int64_t)(due - now);
            else if (now - due > MAX_BEHIND_NS) { /* the host is too slow: slip */
                wall_base = now;
                sim_base_ns = sim_ns;
            }
        }
        if (wait_ns > 20000000)
            wait_ns = 20000000;

        if (out_dirty) {
            fflush(stdout);
            out_dirty = 0;
        }
        struct pollfd fds[2] = {{.fd = STDIN_FILENO, .events = POLLIN}, {.fd = -1}};
        if (pty_master >= 0) {
            fds[1].fd = pty_master;
            fds[1].events = ring_free(&host_rx) ? POLLIN : 0;
        }
        struct timespec ts = {.tv_sec = 0, .tv_nsec = wait_ns};
        int r = ppoll(fds, 2, &ts, NULL);
        if (r < 0 && errno != EINTR)
            break;
        if (r > 0) {
            if (fds[0].revents & (POLLIN | POLLHUP | POLLERR))
                if (!read_commands())
                    quitting = 1;
            if (pty_master >= 0 && (fds[1].revents & POLLIN))
                pty_read();
        }
        if (!halted)
            feeder_start();
        if (halted && avr->state != cpu_Done && avr->state != cpu_Crashed)
            halted = 0; /* `reset` restarted it */
        if (out_dirty) {
            fflush(stdout);
            out_dirty = 0;
        }
    }
    pty_close();
    fflush(stdout);
    avr_terminate(avr);
    return 0;
}
