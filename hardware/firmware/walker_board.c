/*
 * walker_board.c - firmware of the walker's encoder/brake board (Arduino Uno,
 * ATmega328P at 16 MHz), plain C with avr-libc.
 *
 * It speaks the serial line protocol version 1 of PROTOCOL.md (this folder), which
 * is the contract; this file only adds how the board meets it:
 *
 *  - Encoders: left A = PD2 (INT0), left B = PD4 (PCINT20), right A = PD3 (INT1),
 *    right B = PD5 (PCINT21), internal pull-ups. INT0, INT1 (any edge) and PCINT2
 *    all run the same handler, which reads PIND once and decodes both wheels with a
 *    16-entry transition table (x4 decoding: every edge of both channels counts).
 *    A wheel counts up when A leads B. A transition in which both channels of a
 *    wheel changed is a quadrature error: counted, not counted as motion.
 *  - Brakes: left on PB1 (D9, OC1A), right on PB2 (D10, OC1B), Timer1 fast PWM
 *    8-bit, prescaler 64 (976.6 Hz), non-inverting. Duty 0 disconnects the compare
 *    output, so the pin is held low by PORTB (which is 0 from initialisation on).
 *  - Clock: Timer2 in CTC mode, prescaler 64, OCR2A 249: an interrupt every
 *    1000 us. The board time in us is 1000 per interrupt + TCNT2 * 4 (uint32, wraps
 *    after 2^32 us). The same 1 ms interrupt samples the tick reports (so their t_us
 *    are the period apart, to the 4 us of TCNT2), runs the 300 ms command timeout and
 *    schedules the 1 s status line. The interrupt handlers are kept short (no 32-bit
 *    multiply, no calls): both encoders at 12 us per edge are still counted exactly.
 *  - UART0 at 115200 8N1: U2X0 = 1, UBRR0 = 16 (117647 baud, +2.1 %).
 *    Interrupt-driven RX ring (128 bytes) and TX ring (256 bytes); lines are parsed
 *    in the main loop. A line during which received bytes were lost (RX ring full
 *    or a data overrun) is discarded and counted in rx_overflow.
 *  - Tick reports: a report is sampled every period; if the TX ring has no room for
 *    it when the main loop formats it (the rate asks for more than the UART can
 *    carry), it is dropped, and its seq is skipped, so the host sees the gap.
 *  - Command timeout: a valid B line restarts a millisecond counter from the
 *    millisecond its newline arrived (the receive interrupt stamps every byte, so
 *    the time the main loop takes to reach the line does not extend it); at its
 *    299th tick (298-299 ms after the newline, whatever the phase of the millisecond
 *    clock) both duties go to 0 (in the 1 ms interrupt, so a slow main loop cannot
 *    delay it). cmd_timeouts counts the timeouts that released a non-zero duty.
 *  - cmd_seq_gaps: a B line whose seq is ahead of the previous one by d (modulo
 *    2^32, d < 2^31) adds d - 1; a seq that did not move forward (a restarted host)
 *    adds nothing.
 *  - Watchdog: MCUSR is captured and cleared and the watchdog disabled in .init3
 *    (after a watchdog reset it stays enabled at its shortest period); once set up
 *    the watchdog runs at 250 ms and only the main loop resets it.
 *  - At boot the firmware sends an empty line before its H line: a reset can cut a
 *    line short, and the newline ends that partial line (which the host discards)
 *    so that the H line arrives whole. The host's codec skips empty lines.
 *  - The main loop sleeps (idle mode) when it has nothing to do; any interrupt,
 *    at the latest the 1 ms clock, wakes it.
 *  - Gyro (optional): an InvenSense MPU-6050 on the I2C bus (TWI: SDA = PC4/A4,
 *    SCL = PC5/A5, 400 kHz, internal pull-ups besides the module's) at address 0x68.
 *    At boot the firmware reads WHO_AM_I; if 0x68 answers it wakes the chip (PLL
 *    clock), sets the gyro to +-250 deg/s (131 LSB per deg/s), its low-pass filter to
 *    42 Hz and its sample rate to 1 kHz, announces the scale in H and appends the z
 *    rate (GYRO_ZOUT, int16) to every T line, read by the main loop as it formats the
 *    line. The TWI interrupt runs each transfer step by step; the main loop waits at
 *    most 2 ms for one (a dead bus cannot hang it). No IMU, or a read that fails:
 *    the field is left out.
 *
 * Build: make (Makefile in this folder); COUNTS_PER_REV from `make CPR=...`.
 * WALKER_TEST_HOOKS (the test build, build/walker_board_test.elf) adds one host
 * line, `X,1` (with its CRC): the MCU hangs with interrupts disabled, so the tests
 * can check that the watchdog resets it. It is never in the production build.
 */

#include <avr/interrupt.h>
#include <avr/io.h>
#include <avr/sleep.h>
#include <avr/wdt.h>
#include <stdint.h>
#include <stdlib.h>
#include <util/atomic.h>
#include <util/delay.h>

#define PROTOCOL_VERSION 1
#ifdef WALKER_TEST_HOOKS
#define FIRMWARE_VERSION "1.0.0-test"
#else
#define FIRMWARE_VERSION "1.0.0"
#endif
#ifndef COUNTS_PER_REV
#define COUNTS_PER_REV 256
#endif

#define DEFAULT_RATE_HZ 100
#define MAX_RATE_HZ 500
#define CMD_TIMEOUT_MS 300
#define STATUS_PERIOD_MS 1000
#define MAX_LINE 96 /* bytes of a line, '*CC' included, '\n' not (an S line: <= 92) */

#define ENC_MASK (_BV(PD2) | _BV(PD3) | _BV(PD4) | _BV(PD5))

#define IMU_ADDR 0x68          /* MPU-6050 with AD0 low */
#define IMU_WHO_AM_I_VALUE 0x68
#define GYRO_LSB_PER_10DPS 1310 /* FS_SEL 0: 131 LSB per deg/s, announced in H */

/* ---------------------------------------------------------------- reset flags -- */

uint8_t mcusr_at_boot __attribute__((section(".noinit")));

/* Runs before the C runtime initialisation: keep the reset cause, clear it (the
 * watchdog cannot be disabled while WDRF is set) and stop the watchdog. */
void early_boot(void) __attribute__((naked, used, section(".init3")));
void early_boot(void)
{
    mcusr_at_boot = MCUSR;
    MCUSR = 0;
    wdt_disable();
}

/* -------------------------------------------------------------------- encoders -- */

/* index: previous state << 2 | new state, state = A << 1 | B.
 * +1: A leads B, -1: B leads A, 0: no change, 2: both channels changed. */
#define QERR 2
static const int8_t quad_table[16] = {
    /* prev 00 */ 0, -1, +1, QERR,
    /* prev 01 */ +1, 0, QERR, -1,
    /* prev 10 */ -1, QERR, 0, +1,
    /* prev 11 */ QERR, +1, -1, 0,
};

typedef struct {
    uint32_t count; /* int32 on the wire, wraps modulo 2^32 */
    uint8_t state;
} wheel_t;

static volatile wheel_t enc_left, enc_right;
static volatile uint32_t quad_errors;
static volatile uint8_t quad_error_flag; /* since the last tick report */

static inline uint8_t left_state(uint8_t pins)
{
    return (uint8_t)(((pins >> PD2) & 1) << 1 | ((pins >> PD4) & 1));
}

static inline uint8_t right_state(uint8_t pins)
{
    return (uint8_t)(((pins >> PD3) & 1) << 1 | ((pins >> PD5) & 1));
}

/* Inlined into the one encoder handler (a call would make it save every register). */
static inline __attribute__((always_inline)) void wheel_update(volatile wheel_t *w, uint8_t now)
{
    uint8_t prev = w->state;
    if (now == prev)
        return; /* the other wheel's edge */
    w->state = now;
    int8_t d = quad_table[(uint8_t)(prev << 2 | now)];
    if (d == QERR) {
        quad_errors++;
        quad_error_flag = 1;
    } else if (d > 0) {
        w->count++;
    } else {
        w->count--;
    }
}

ISR(INT0_vect)
{
    uint8_t pins = PIND;
    wheel_update(&enc_left, left_state(pins));
    wheel_update(&enc_right, right_state(pins));
}
ISR(INT1_vect, ISR_ALIASOF(INT0_vect));
ISR(PCINT2_vect, ISR_ALIASOF(INT0_vect));

static void encoders_init(void)
{
    DDRD &= (uint8_t)~ENC_MASK;
    PORTD |= ENC_MASK; /* pull-ups */
    uint8_t pins = PIND;
    enc_left.state = left_state(pins);
    enc_right.state = right_state(pins);
    EICRA = _BV(ISC10) | _BV(ISC00); /* INT0, INT1: any logical change */
    EIFR = _BV(INTF1) | _BV(INTF0);
    EIMSK = _BV(INT1) | _BV(INT0);
    PCMSK2 = _BV(PCINT20) | _BV(PCINT21);
    PCIFR = _BV(PCIF2);
    PCICR = _BV(PCIE2);
}

/* ---------------------------------------------------------------------- brakes -- */

static volatile uint8_t pwm_left, pwm_right;

/* Interrupts must be disabled (OCR1x are 16-bit registers; the 1 ms interrupt
 * also calls it). Duty 0 disconnects the output: PORTB holds the pin low. */
static void brakes_apply(uint8_t left, uint8_t right)
{
    uint8_t tccr = TCCR1A;
    if (left) {
        OCR1A = left;
        tccr |= _BV(COM1A1);
    } else {
        tccr &= (uint8_t)~(_BV(COM1A1) | _BV(COM1A0));
    }
    if (right) {
        OCR1B = right;
        tccr |= _BV(COM1B1);
    } else {
        tccr &= (uint8_t)~(_BV(COM1B1) | _BV(COM1B0));
    }
    TCCR1A = tccr;
    if (!left)
        OCR1A = 0;
    if (!right)
        OCR1B = 0;
    pwm_left = left;
    pwm_right = right;
}

static void brakes_init(void)
{
    PORTB &= (uint8_t)~(_BV(PB1) | _BV(PB2));
    DDRB |= _BV(PB1) | _BV(PB2);
    OCR1A = 0;
    OCR1B = 0;
    TCCR1A = _BV(WGM10);                           /* fast PWM 8-bit (mode 5), */
    TCCR1B = _BV(WGM12) | _BV(CS11) | _BV(CS10);   /* prescaler 64: 976.6 Hz */
}

/* ---------------------------------------------------------------- gyro (I2C) -- */

/* MPU-6050 registers (Register Map RM-MPU-6000A-00) */
#define MPU_SMPLRT_DIV 0x19
#define MPU_CONFIG 0x1A
#define MPU_GYRO_CONFIG 0x1B
#define MPU_GYRO_ZOUT_H 0x47
#define MPU_PWR_MGMT_1 0x6B
#define MPU_WHO_AM_I 0x75

#define TW_STATUS (TWSR & 0xF8)
#define TWI_WAIT_US 2000u /* a transfer takes ~200 us at 400 kHz; give up after 2 ms */

/* An I2C transfer with the IMU, driven by the TWI interrupt one bus step at a time
 * (as the Arduino Wire library does): write `len` bytes to, or read them from, the
 * registers from `reg` on. The phase says what the last step was, so each step checks
 * the status it must have produced. */
enum {
    TWI_START_SENT,
    TWI_SLA_W_SENT,
    TWI_REG_SENT,
    TWI_DATA_SENT,
    TWI_RESTART_SENT,
    TWI_SLA_R_SENT,
    TWI_RECEIVING,
};

static volatile uint8_t twi_buf[2];
static volatile uint8_t twi_reg, twi_len, twi_pos, twi_writing, twi_phase;
static volatile uint8_t twi_busy, twi_ok;
static uint8_t imu_present;

#define TWI_STEP(extra) (TWCR = (uint8_t)(_BV(TWINT) | _BV(TWEN) | _BV(TWIE) | (extra)))

static void twi_finish(uint8_t ok)
{
    TWCR = _BV(TWINT) | _BV(TWEN) | _BV(TWSTO); /* stop; the interrupt off */
    twi_ok = ok;
    twi_busy = 0;
}

/* The next byte to receive, acknowledged unless it is the last. */
static void twi_receive_next(void)
{
    twi_phase = TWI_RECEIVING;
    TWI_STEP(twi_pos + 1 < twi_len ? _BV(TWEA) : 0);
}

ISR(TWI_vect)
{
    uint8_t st = TW_STATUS;
    switch (twi_phase) {
    case TWI_START_SENT:
        if (st != 0x08)
            break;
        TWDR = IMU_ADDR << 1;
        twi_phase = TWI_SLA_W_SENT;
        TWI_STEP(0);
        return;
    case TWI_SLA_W_SENT: /* simavr 1.6 reports an acknowledged SLA+W as 0x28 */
        if (st != 0x18 && st != 0x28)
            break;
        TWDR = twi_reg;
        twi_phase = TWI_REG_SENT;
        TWI_STEP(0);
        return;
    case TWI_REG_SENT:
    case TWI_DATA_SENT:
        if (st != 0x28)
            break;
        if (!twi_writing) {
            twi_phase = TWI_RESTART_SENT;
            TWI_STEP(_BV(TWSTA));
        } else if (twi_pos < twi_len) {
            TWDR = twi_buf[twi_pos++];
            twi_phase = TWI_DATA_SENT;
            TWI_STEP(0);
        } else {
            twi_finish(1);
        }
        return;
    case TWI_RESTART_SENT:
        if (st != 0x10)
            break;
        TWDR = IMU_ADDR << 1 | 1;
        twi_phase = TWI_SLA_R_SENT;
        TWI_STEP(0);
        return;
    case TWI_SLA_R_SENT:
        if (st != 0x40)
            break;
        twi_receive_next();
        return;
    case TWI_RECEIVING:
        if (st != 0x50 && st != 0x58)
            break;
        twi_buf[twi_pos++] = TWDR;
        if (twi_pos < twi_len)
            twi_receive_next();
        else
            twi_finish(1);
        return;
    }
    twi_finish(0); /* not acknowledged, or the bus did something else */
}

/* One transfer, waited for with interrupts on (the main loop calls it). */
static uint8_t twi_transfer(uint8_t reg, uint8_t len, uint8_t writing)
{
    uint16_t us = TWI_WAIT_US;
    while ((TWCR & _BV(TWSTO)) && --us) /* the previous stop still on the bus */
        _delay_us(1);
    twi_reg = reg;
    twi_len = len;
    twi_pos = 0;
    twi_writing = writing;
    twi_phase = TWI_START_SENT;
    twi_busy = 1;
    TWI_STEP(_BV(TWSTA));
    for (us = TWI_WAIT_US; twi_busy; us--) {
        if (!us) { /* a dead bus: drop the transfer, start the TWI afresh */
            TWCR = 0;
            twi_busy = 0;
            TWCR = _BV(TWEN);
            return 0;
        }
        _delay_us(1);
    }
    return twi_ok;
}

static uint8_t imu_write(uint8_t reg, uint8_t value)
{
    twi_buf[0] = value;
    return twi_transfer(reg, 1, 1);
}

static uint8_t imu_read(uint8_t reg, uint8_t n)
{
    return twi_transfer(reg, n, 0);
}

/* Finds and sets up the IMU; imu_present says whether it answered. */
static void imu_init(void)
{
    PORTC |= _BV(PC4) | _BV(PC5); /* pull-ups: a bus without a module reads idle */
    TWSR = 0;                     /* prescaler 1 */
    TWBR = 12;                    /* SCL = F_CPU / (16 + 2 * 12) = 400 kHz */
    TWCR = _BV(TWEN);
    imu_present = imu_read(MPU_WHO_AM_I, 1) && twi_buf[0] == IMU_WHO_AM_I_VALUE &&
                  imu_write(MPU_PWR_MGMT_1, 0x01) && /* awake, PLL with the X gyro */
                  imu_write(MPU_SMPLRT_DIV, 0) &&   /* 1 kHz with the filter on */
                  imu_write(MPU_CONFIG, 3) &&       /* DLPF: gyro 42 Hz, 4.8 ms */
                  imu_write(MPU_GYRO_CONFIG, 0);    /* +-250 deg/s */
    if (!imu_present)
        TWCR = 0; /* the TWI off: PC4, PC5 back to plain pins */
}

/* The gyro's z rate in LSB; 0 if there is no IMU or the read failed. */
static uint8_t imu_gyro_z(int16_t *rate)
{
    if (!imu_present || !imu_read(MPU_GYRO_ZOUT_H, 2))
        return 0;
    *rate = (int16_t)((uint16_t)twi_buf[0] << 8 | twi_buf[1]);
    return 1;
}

/* ------------------------------------------------------------- clock, schedule -- */

static volatile uint32_t us_at_tick; /* board time at the last 1 ms tick */
static volatile uint16_t cmd_age_ms;
static volatile uint8_t ms8; /* milliseconds, modulo 256: the receive stamps */
static volatile uint8_t cmd_timed_out = 1; /* brakes released until the first B */
static volatile uint32_t cmd_timeouts;
static volatile uint16_t report_period_ms = (1000 + DEFAULT_RATE_HZ / 2) / DEFAULT_RATE_HZ;
static volatile uint16_t report_ms;
static volatile uint16_t status_ms;
static volatile uint8_t status_due;

typedef struct {
    uint32_t seq, t_us, left, right;
    uint8_t pwm_left, pwm_right, flags;
} tick_t;

static volatile tick_t tick_pending;
static volatile uint8_t tick_ready;
static volatile uint32_t tick_seq;

/* Board time in us; interrupts must be disabled. */
static uint32_t now_us(void)
{
    uint32_t us = us_at_tick;
    uint8_t t = TCNT2;
    if ((TIFR2 & _BV(OCF2A)) && t < 125) /* the 1 ms interrupt is pending */
        us += 1000u;
    return us + (uint16_t)(t * 4u);
}

ISR(TIMER2_COMPA_vect)
{
    us_at_tick += 1000u;
    ms8++;
    /* the tick that makes the age CMD_TIMEOUT_MS - 1 comes 298-299 ms after the
     * command was parsed: released within 300 ms of its newline, whatever the phase */
    if (!cmd_timed_out && ++cmd_age_ms >= CMD_TIMEOUT_MS - 1) {
        if (pwm_left || pwm_right)
            cmd_timeouts++;
        brakes_apply(0, 0);
        cmd_timed_out = 1;
    }
    if (++report_ms >= report_period_ms) {
        report_ms = 0;
        tick_pending.seq = tick_seq++;
        tick_pending.t_us = now_us();
        tick_pending.left = enc_left.count;
        tick_pending.right = enc_right.count;
        tick_pending.pwm_left = pwm_left;
        tick_pending.pwm_right = pwm_right;
        tick_pending.flags = (uint8_t)((cmd_timed_out ? 0x01 : 0) | (quad_error_flag ? 0x02 : 0));
        quad_error_flag = 0;
        tick_ready = 1;
    }
    if (++status_ms >= STATUS_PERIOD_MS) {
        status_ms = 0;
        status_due = 1;
    }
}

static void clock_init(void)
{
    TCCR2A = _BV(WGM21); /* CTC */
    OCR2A = 249;         /* 250 counts of 4 us */
    TIFR2 = _BV(OCF2A);
    TIMSK2 = _BV(OCIE2A);
    TCCR2B = _BV(CS22); /* prescaler 64 */
}

/* ------------------------------------------------------------------------ UART -- */

#define RX_SIZE 128
#define TX_SIZE 256

static volatile uint8_t rx_buf[RX_SIZE];
static volatile uint8_t rx_ms8[RX_SIZE]; /* ms8 when each byte arrived */
static volatile uint8_t rx_head, rx_tail;
static volatile uint8_t rx_lost;
static volatile uint8_t tx_buf[TX_SIZE];
static volatile uint8_t tx_head, tx_tail;

ISR(USART_RX_vect)
{
    uint8_t status = UCSR0A;
    uint8_t c = UDR0;
    uint8_t next = (uint8_t)((rx_head + 1) % RX_SIZE);
    if (status & _BV(DOR0))
        rx_lost = 1;
    if (next == rx_tail) {
        rx_lost = 1;
        return;
    }
    rx_buf[rx_head] = c;
    rx_ms8[rx_head] = ms8;
    rx_head = next;
}

ISR(USART_UDRE_vect)
{
    if (tx_head == tx_tail) {
        UCSR0B &= (uint8_t)~_BV(UDRIE0);
        return;
    }
    UDR0 = tx_buf[tx_tail];
    tx_tail = (uint8_t)(tx_tail + 1); /* TX_SIZE is 256 */
}

static void uart_init(void)
{
    UCSR0A = _BV(U2X0);
    UCSR0C = _BV(UCSZ01) | _BV(UCSZ00); /* 8N1 */
    UBRR0H = 0;
    UBRR0L = 16;
    UCSR0B = _BV(RXEN0) | _BV(TXEN0) | _BV(RXCIE0);
}

static uint8_t tx_free(void)
{
    uint8_t used;
    ATOMIC_BLOCK(ATOMIC_RESTORESTATE) { used = (uint8_t)(tx_head - tx_tail); }
    return (uint8_t)(TX_SIZE - 1 - used);
}

/* Queues a whole line; waits for room unless `droppable` (then returns 0 if the line
 * does not fit). Only the main loop calls it, so waiting resets the watchdog. */
static uint8_t tx_line(const char *s, uint8_t len, uint8_t droppable)
{
    while (tx_free() < len) {
        if (droppable)
            return 0;
        wdt_reset();
    }
    for (uint8_t i = 0; i < len; i++) {
        tx_buf[tx_head] = (uint8_t)s[i];
        ATOMIC_BLOCK(ATOMIC_RESTORESTATE) { tx_head = (uint8_t)(tx_head + 1); }
    }
    UCSR0B |= _BV(UDRIE0);
    return 1;
}

/* ---------------------------------------------------------------- line framing -- */

static uint8_t crc8(const char *s, uint8_t len)
{
    uint8_t c = 0;
    for (uint8_t i = 0; i < len; i++) {
        c ^= (uint8_t)s[i];
        for (uint8_t b = 0; b < 8; b++)
            c = (c & 0x80) ? (uint8_t)((c << 1) ^ 0x07) : (uint8_t)(c << 1);
    }
    return c;
}

/* The longest line the board can make is an S line with every counter at 10 digits:
 * 92 bytes, within MAX_LINE; the buffer holds it whole. */
#define OUT_SIZE 100

typedef struct {
    char buf[OUT_SIZE];
    uint8_t len;
} out_line_t;

static void out_begin(out_line_t *o, char kind)
{
    o->buf[0] = kind;
    o->len = 1;
}

static void out_str(out_line_t *o, const char *s)
{
    o->buf[o->len++] = ',';
    while (*s && o->len < OUT_SIZE - 5) /* room for '*CC\n' */
        o->buf[o->len++] = *s++;
}

static void out_u32(out_line_t *o, uint32_t v)
{
    char digits[11];
    ultoa(v, digits, 10);
    out_str(o, digits);
}

static void out_i32(out_line_t *o, int32_t v)
{
    char digits[12];
    ltoa(v, digits, 10);
    out_str(o, digits);
}

static char hex_digit(uint8_t v)
{
    return (char)(v < 10 ? '0' + v : 'A' + v - 10);
}

static uint8_t out_send(out_line_t *o, uint8_t droppable)
{
    uint8_t c = crc8(o->buf, o->len);
    o->buf[o->len++] = '*';
    o->buf[o->len++] = hex_digit(c >> 4);
    o->buf[o->len++] = hex_digit(c & 0x0F);
    o->buf[o->len++] = '\n';
    return tx_line(o->buf, o->len, droppable);
}

/* ------------------------------------------------------------- board -> host -- */

static uint16_t report_rate_hz = DEFAULT_RATE_HZ;
static uint32_t rx_lines, rx_bad_crc, rx_malformed, rx_overflow;
static uint32_t cmd_seq_gaps, last_cmd_seq;
static uint8_t have_cmd_seq;

static void send_handshake(void)
{
    out_line_t o;
    out_begin(&o, 'H');
    out_u32(&o, PROTOCOL_VERSION);
    out_str(&o, FIRMWARE_VERSION);
    out_u32(&o, report_rate_hz);
    out_u32(&o, COUNTS_PER_REV);
    out_u32(&o, mcusr_at_boot & 0x0F);
    if (imu_present)
        out_u32(&o, GYRO_LSB_PER_10DPS);
    out_send(&o, 0);
}

static void send_status(void)
{
    uint32_t timeouts, qerr;
    ATOMIC_BLOCK(ATOMIC_RESTORESTATE)
    {
        timeouts = cmd_timeouts;
        qerr = quad_errors;
    }
    out_line_t o;
    out_begin(&o, 'S');
    out_u32(&o, rx_lines);
    out_u32(&o, rx_bad_crc);
    out_u32(&o, rx_malformed);
    out_u32(&o, rx_overflow);
    out_u32(&o, timeouts);
    out_u32(&o, cmd_seq_gaps);
    out_u32(&o, qerr);
    out_u32(&o, last_cmd_seq);
    out_send(&o, 0);
}

static void send_tick(void)
{
    tick_t t;
    ATOMIC_BLOCK(ATOMIC_RESTORESTATE)
    {
        t.seq = tick_pending.seq;
        t.t_us = tick_pending.t_us;
        t.left = tick_pending.left;
        t.right = tick_pending.right;
        t.pwm_left = tick_pending.pwm_left;
        t.pwm_right = tick_pending.pwm_right;
        t.flags = tick_pending.flags;
        tick_ready = 0;
    }
    int16_t gyro_z;
    uint8_t have_gyro = imu_gyro_z(&gyro_z);
    out_line_t o;
    out_begin(&o, 'T');
    out_u32(&o, t.seq);
    out_u32(&o, t.t_us);
    out_i32(&o, (int32_t)t.left);
    out_i32(&o, (int32_t)t.right);
    out_u32(&o, t.pwm_left);
    out_u32(&o, t.pwm_right);
    out_u32(&o, t.flags);
    if (have_gyro)
        out_i32(&o, gyro_z);
    out_send(&o, 1);
}

/* ------------------------------------------------------------- host -> board -- */

typedef struct {
    const char *s;
    uint8_t len;
} field_t;

/* A field as the protocol allows: -?[0-9]{1,11}, then within [lo, hi] (every host
 * field is unsigned, so a minus sign only passes on a zero: "-0" is 0). */
static uint8_t parse_u32(field_t f, uint32_t lo, uint32_t hi, uint32_t *out)
{
    uint8_t i = 0, neg = 0, big = 0;
    if (f.len && f.s[0] == '-') {
        neg = 1;
        i = 1;
    }
    uint8_t ndigits = (uint8_t)(f.len - i);
    if (ndigits < 1 || ndigits > 11)
        return 0;
    uint32_t v = 0;
    for (; i < f.len; i++) {
        char c = f.s[i];
        if (c < '0' || c > '9')
            return 0;
        uint8_t d = (uint8_t)(c - '0');
        if (v > 429496729UL || (v == 429496729UL && d > 5))
            big = 1; /* beyond uint32: out of every range */
        v = v * 10 + d;
    }
    if (big || (neg && v != 0) || v < lo || v > hi)
        return 0;
    *out = v;
    return 1;
}

static int8_t hex_value(char c)
{
    if (c >= '0' && c <= '9')
        return (int8_t)(c - '0');
    if (c >= 'A' && c <= 'F')
        return (int8_t)(c - 'A' + 10);
    if (c >= 'a' && c <= 'f')
        return (int8_t)(c - 'a' + 10);
    return -1;
}

#define MAX_FIELDS 4

#ifdef WALKER_TEST_HOOKS
static void test_hang(void)
{
    cli();
    for (;;) {
    }
}

/* The main loop busy for ms milliseconds, interrupts on (lines arriving meanwhile wait
 * in the receive ring, as behind a slow report) */
static void test_busy(uint8_t ms)
{
    while (ms--)
        _delay_ms(1);
}
#endif

static void set_rate(uint16_t rate)
{
    uint16_t period = (uint16_t)((1000u + rate / 2) / rate);
    ATOMIC_BLOCK(ATOMIC_RESTORESTATE)
    {
        report_period_ms = period;
        report_ms = 0;
    }
    report_rate_hz = rate;
}

static uint8_t line_ms8; /* ms8 when the newline of the line being handled arrived */

static void handle_brake(uint32_t seq, uint8_t left, uint8_t right)
{
    if (have_cmd_seq) {
        uint32_t d = seq - last_cmd_seq;
        if (d != 0 && d < 0x80000000UL)
            cmd_seq_gaps += d - 1;
    }
    last_cmd_seq = seq;
    have_cmd_seq = 1;
    ATOMIC_BLOCK(ATOMIC_RESTORESTATE)
    {
        brakes_apply(left, right);
        /* the age since the newline arrived (the main loop reaches a line well within
         * the 250 ms watchdog, so modulo 256 is unambiguous) */
        cmd_age_ms = (uint8_t)(ms8 - line_ms8);
        cmd_timed_out = 0;
    }
}

/* One received line, '\n' removed. Never acts on a bad line. */
static void handle_line(char *s, uint8_t len)
{
    if (len && s[len - 1] == '\r')
        len--;
    if (len == 0)
        return; /* an empty line is not a line */
    if (len > MAX_LINE) {
        rx_overflow++;
        return;
    }
    int16_t star = -1;
    for (uint8_t i = 0; i < len; i++)
        if (s[i] == '*')
            star = i;
    if (star < 0 || len - star - 1 != 2) {
        rx_malformed++;
        return;
    }
    int8_t hi = hex_value(s[star + 1]), lo = hex_value(s[star + 2]);
    if (hi < 0 || lo < 0) {
        rx_malformed++;
        return;
    }
    if (crc8(s, (uint8_t)star) != (uint8_t)(hi << 4 | lo)) {
        rx_bad_crc++;
        return;
    }
    /* split the payload into the type and its fields */
    field_t fields[MAX_FIELDS];
    uint8_t nfields = 0;
    uint8_t type_len = 0;
    uint8_t i = 0;
    while (i < star && s[i] != ',')
        i++;
    type_len = i;
    while (i < star && nfields < MAX_FIELDS) {
        uint8_t start = (uint8_t)(i + 1);
        uint8_t j = start;
        while (j < star && s[j] != ',')
            j++;
        fields[nfields].s = s + start;
        fields[nfields].len = (uint8_t)(j - start);
        nfields++;
        i = j;
    }
    if (type_len != 1) {
        rx_malformed++;
        return;
    }
    uint32_t a, b, c;
    switch (s[0]) {
    case 'Q':
        rx_lines++;
        send_handshake();
        send_status();
        return;
    case 'B':
        if (nfields < 3 || !parse_u32(fields[0], 0, 0xFFFFFFFFUL, &a) ||
            !parse_u32(fields[1], 0, 255, &b) || !parse_u32(fields[2], 0, 255, &c))
            break;
        rx_lines++;
        handle_brake(a, (uint8_t)b, (uint8_t)c);
        return;
    case 'C':
        if (nfields < 1 || !parse_u32(fields[0], 1, MAX_RATE_HZ, &a))
            break;
        rx_lines++;
        set_rate((uint16_t)a);
        send_handshake();
        return;
#ifdef WALKER_TEST_HOOKS
    case 'X': /* X,1: hang with interrupts off; X,2,MS: keep the main loop busy MS ms */
        if (nfields < 1 || !parse_u32(fields[0], 1, 2, &a))
            break;
        if (a == 2) {
            if (nfields < 2 || !parse_u32(fields[1], 1, 100, &b))
                break;
            rx_lines++;
            test_busy((uint8_t)b);
            return;
        }
        rx_lines++;
        test_hang();
        return;
#endif
    default:
        break;
    }
    rx_malformed++;
}

static char line_buf[MAX_LINE + 2];
static uint8_t line_len;
static uint8_t line_overflow;

static void receive_byte(uint8_t c)
{
    if (c == '\n') {
        if (line_overflow)
            rx_overflow++;
        else
            handle_line(line_buf, line_len);
        line_len = 0;
        line_overflow = 0;
    } else if (!line_overflow) {
        if (line_len < MAX_LINE + 1) /* room for a '\r' */
            line_buf[line_len++] = (char)c;
        else
            line_overflow = 1;
    }
}

static void receive(void)
{
    for (;;) {
        uint8_t c, lost;
        ATOMIC_BLOCK(ATOMIC_RESTORESTATE)
        {
            lost = rx_lost;
            rx_lost = 0;
        }
        if (lost)
            line_overflow = 1;
        if (rx_tail == rx_head)
            return;
        c = rx_buf[rx_tail];
        line_ms8 = rx_ms8[rx_tail];
        ATOMIC_BLOCK(ATOMIC_RESTORESTATE) { rx_tail = (uint8_t)((rx_tail + 1) % RX_SIZE); }
        receive_byte(c);
    }
}

/* ------------------------------------------------------------------------ main -- */

int main(void)
{
    brakes_init(); /* released from reset on */
    encoders_init();
    clock_init();
    uart_init();
    set_sleep_mode(SLEEP_MODE_IDLE);
    wdt_enable(WDTO_250MS);
    sei();
    imu_init(); /* its transfers run on the TWI interrupt */
    tx_line("\n", 1, 0); /* ends a line a reset cut short, so the host gets H whole */
    send_handshake();

    for (;;) {
        wdt_reset();
        receive();
        if (tick_ready)
            send_tick();
        if (status_due) {
            status_due = 0;
            send_status();
        }
        cli();
        if (rx_tail == rx_head && !tick_ready && !status_due && !rx_lost) {
            sleep_enable();
            sei();
            sleep_cpu(); /* the instruction after sei runs before any interrupt */
            sleep_disable();
        }
        sei();
    }
}
