"""fakenect recordings: the folder format, a writer, and replay through the real sync API.

fakenect (libfreenect's `fakenect/`, Debian package libfreenect-bin) replays a recorded
folder through a fake libfreenect that a program loads in place of the real one. The
format, as libfreenect 0.5.3's `fakenect/record.c` writes it and `fakenect/fakenect.c`
reads it:

- ``INDEX.txt``: one file name per line, in playback order.
- A file name is ``<type>-<time>-<timestamp>.<ext>``: type ``d`` depth, ``r`` video
  (RGB), ``a`` accelerometer state; time is the recording host's clock in seconds
  (printf ``%f``), timestamp the Kinect's frame timestamp (``%u``, 60 MHz ticks,
  wrapping at 2^32). The reader parses it with ``sscanf("%c-%lf-%u")``.
- A depth file is the line ``P5 640 480 65535`` and a newline, then 640×480 uint16
  11-bit raw values in the recording host's byte order (little-endian on x86 and ARM):
  *not* the big-endian of a standard PGM. A video file is ``P6 640 480 255``, a newline,
  then 640×480×3 uint8 RGB. The reader skips the first line and copies the frame's
  bytes; only 640×480 11-bit depth and RGB video exist (other formats abort).
- Playback sleeps between lines for the recorded time difference minus the time
  already spent, so frames come at the recorded pace. A time of 0 counts as "no
  previous line" (no pacing), so times must be > 0.
- At the end of INDEX.txt the fake library's event loop returns an error; the sync API's
  thread then stops and frees its frame buffers, and a later ``sync_get_*`` blocks for
  ever. Playback does not loop.

`FakenectWriter` writes such a folder from arrays. `ReplayFolder` prepares a folder
for replay by `hardware.depth` (which runs the capture in `hardware.kinect_worker` with
`replay_environment`):

- it links every recorded file into a temporary folder under a name whose timestamp
  field is the line number, so each frame that comes out of libfreenect says which line
  it was (the recorded timestamps are kept in `entries` and given back by the caller):
  the replay knows exactly when a stream has delivered its last frame and which frames
  the sync API's buffer ring dropped;
- it appends a line whose recorded time lies 10^6 s after the last one, of a type the
  fake library ignores: after the last frame the library sleeps instead of reaching the
  end of the index, so it never frees the buffer that the last frame is still being
  copied from, and that frame stays in the ring until it is read;
- when the recording has depth and video, it puts two such lines 0.2 s apart before the
  first frame, so that both streams (which the sync API sets up only between two
  lines) are running when the first frame plays.

Debian's fake library lacks `freenect_camera_to_world`, which `libfreenect_sync`
imports, so the sync API (and the Python binding) cannot load with it alone.
`fakenect_shim` compiles a one-function library that provides it, into the user's cache
folder (``$XDG_CACHE_HOME/walker-slam``, else ``~/.cache/walker-slam``), once per
version of its source.
"""

from __future__ import annotations

import hashlib
import math
import os
import re
import shutil
import subprocess
import sysconfig
import tempfile
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from hardware.errors import DeviceError

WIDTH = 640
HEIGHT = 480
TICKS_PER_S = 60_000_000  # the Kinect's frame timestamp clock
TICK_WRAP = 2**32
RAW_MAX = 2047  # 11-bit raw disparity; 2047 means no reading
DEPTH_HEADER = f"P5 {WIDTH} {HEIGHT} 65535\n".encode()
VIDEO_HEADER = f"P6 {WIDTH} {HEIGHT} 255\n".encode()
SENTINEL_DELAY_S = 1e6
PREAMBLE_S = 0.2

# sscanf("%c-%lf-%u-%*s"): a type character, a decimal number, an unsigned integer.
_NAME = re.compile(r"^(?P<type>.)-(?P<time>[-+]?(?:\d+\.?\d*|\.\d+)(?:[eE][-+]?\d+)?)-(?P<ts>\d+)")


class FakenectError(DeviceError):
    """A fakenect folder, or what replaying it needs, is missing or malformed (one line)."""


@dataclass(frozen=True)
class IndexEntry:
    """One line of INDEX.txt: its file name, type ('d', 'r', 'a'), time and timestamp."""

    name: str
    type: str
    time: float
    timestamp: int
    time_text: str


def parse_name(name: str) -> IndexEntry:
    """The fields of a fakenect file name, as fakenect's reader parses them."""
    m = _NAME.match(name)
    if m is None:
        raise FakenectError(f"not a fakenect file name (type-time-timestamp.ext): {name!r}")
    ts = int(m["ts"])
    if ts >= TICK_WRAP:
        raise FakenectError(f"timestamp does not fit in 32 bits in {name!r}")
    return IndexEntry(name, m["type"], float(m["time"]), ts, m["time"])


def read_index(folder: str | os.PathLike) -> list[IndexEntry]:
    """The entries of `folder`/INDEX.txt in playback order (empty lines skipped)."""
    folder = Path(folder)
    if not folder.is_dir():
        raise FakenectError(f"fakenect folder not found: {folder}")
    index = folder / "INDEX.txt"
    if not index.is_file():
        raise FakenectError(f"not a fakenect recording (no INDEX.txt): {folder}")
    entries = []
    for n, line in enumerate(index.read_text().splitlines(), start=1):
        if not line:
            continue
        try:
            entries.append(parse_name(line))
        except FakenectError as exc:
            raise FakenectError(f"{index} line {n}: {exc}") from None
    return entries


def _check_depth(raw: np.ndarray) -> np.ndarray:
    raw = np.asarray(raw)
    if raw.shape != (HEIGHT, WIDTH) or raw.dtype.kind not in "ui":
        raise ValueError(
            f"a fakenect depth frame is {HEIGHT}x{WIDTH} integers, got {raw.dtype} {raw.shape}"
        )
    if raw.size and (raw.min() < 0 or raw.max() > RAW_MAX):
        raise ValueError(f"11-bit raw depth must be in 0..{RAW_MAX}")
    return raw.astype("<u2")


def _check_video(rgb: np.ndarray) -> np.ndarray:
    rgb = np.asarray(rgb)
    if rgb.shape != (HEIGHT, WIDTH, 3) or rgb.dtype != np.uint8:
        raise ValueError(
            f"a fakenect video frame is {HEIGHT}x{WIDTH}x3 uint8 RGB, got {rgb.dtype} {rgb.shape}"
        )
    return np.ascontiguousarray(rgb)


class FakenectWriter:
    """Writes a fakenect recording folder from arrays, as `fakenect-record` would.

    `add_depth(raw, t)` takes 480×640 11-bit raw disparities (0..2047, 2047 = no
    reading), `add_video(rgb, t)` 480×640×3 uint8 in **RGB** order (an OpenCV image is
    BGR: pass ``bgr[..., ::-1]``). t is the recording time [s] (> 0, never decreasing:
    playback is paced by its differences); timestamp the Kinect's 60 MHz frame counter,
    by default ``round(t · 60e6) mod 2^32``. Depth is written little-endian (the byte
    order fakenect reads on x86 and ARM hosts). INDEX.txt grows line by line, so a
    folder whose writer was interrupted still plays the frames written so far.
    """

    def __init__(self, folder: str | os.PathLike) -> None:
        self.folder = Path(folder)
        self.folder.mkdir(parents=True, exist_ok=True)
        index = self.folder / "INDEX.txt"
        if index.exists() and index.stat().st_size:
            raise FileExistsError(f"{index} exists: write a recording into a new folder")
        self._index = index.open("w")
        self._last_t = 0.0
        self.entries: list[IndexEntry] = []

    def _add(
        self, type_: str, ext: str, t: float, timestamp: int | None, data: bytes
    ) -> IndexEntry:
        if self._index.closed:
            raise ValueError("FakenectWriter is closed")
        t = float(t)
        if not (math.isfinite(t) and t > 0):
            raise ValueError(f"recording time must be finite and > 0, got {t}")
        if t < self._last_t:
            raise ValueError(f"recording times must not decrease ({t} after {self._last_t})")
        if timestamp is None:
            timestamp = round(t * TICKS_PER_S) % TICK_WRAP
        if not 0 <= int(timestamp) < TICK_WRAP:
            raise ValueError(f"timestamp must fit in 32 bits, got {timestamp}")
        name = f"{type_}-{t:f}-{int(timestamp)}.{ext}"
        path = self.folder / name
        if path.exists():
            raise FileExistsError(
                f"{path} exists (same type, time and timestamp as a frame before)"
            )
        path.write_bytes(data)
        self._index.write(name + "\n")
        self._index.flush()
        self._last_t = t
        entry = parse_name(name)
        self.entries.append(entry)
        return entry

    def add_depth(self, raw: np.ndarray, t: float, timestamp: int | None = None) -> IndexEntry:
        return self._add("d", "pgm", t, timestamp, DEPTH_HEADER + _check_depth(raw).tobytes())

    def add_video(self, rgb: np.ndarray, t: float, timestamp: int | None = None) -> IndexEntry:
        return self._add("r", "ppm", t, timestamp, VIDEO_HEADER + _check_video(rgb).tobytes())

    def close(self) -> None:
        self._index.close()

    def __enter__(self) -> FakenectWriter:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def read_depth_file(path: str | os.PathLike) -> np.ndarray:
    """A recorded depth file's 480×640 raw values (uint16, little-endian on disk)."""
    data = Path(path).read_bytes()
    body = data[data.index(b"\n") + 1 :]
    return (
        np.frombuffer(body, dtype="<u2", count=WIDTH * HEIGHT)
        .reshape(HEIGHT, WIDTH)
        .astype(np.uint16)
    )


def read_video_file(path: str | os.PathLike) -> np.ndarray:
    """A recorded video file's 480×640×3 RGB values."""
    data = Path(path).read_bytes()
    body = data[data.index(b"\n") + 1 :]
    return (
        np.frombuffer(body, dtype=np.uint8, count=WIDTH * HEIGHT * 3)
        .reshape(HEIGHT, WIDTH, 3)
        .copy()
    )


class ReplayFolder:
    """A recording staged for replay (see the module docstring); `close()` removes it.

    entries: the recording's lines; `lines[kind]` the line numbers (0-based, the
    timestamps the staged frames carry) of its depth ('depth') and video ('video')
    frames.
    """

    def __init__(self, folder: str | os.PathLike) -> None:
        self.source = Path(folder).resolve()
        self.entries = read_index(self.source)
        self.lines: dict[str, list[int]] = {"depth": [], "video": []}
        for i, e in enumerate(self.entries):
            if e.type == "d":
                self.lines["depth"].append(i)
            elif e.type == "r":
                self.lines["video"].append(i)
        missing = [e.name for e in self.entries if not (self.source / e.name).is_file()]
        if missing:
            raise FakenectError(
                f"{len(missing)} file(s) listed in {self.source / 'INDEX.txt'} are missing, "
                f"e.g. {missing[0]}"
            )
        self.path = Path(tempfile.mkdtemp(prefix="walkerslam-fakenect-"))
        try:
            names = []
            extra = len(self.entries)
            if self.lines["depth"] and self.lines["video"]:
                # Two ignored lines before the first frame: the library sleeps
                # PREAMBLE_S before the second one, and the sync API sets a stream up
                # only between lines, so a second stream started within that time runs
                # before the first frame (else the first line(s) are lost to it).
                first = self.entries[0].time
                times = [first - 2 * PREAMBLE_S, first - PREAMBLE_S]
                if times[0] == 0.0:  # a time of 0 would disable the pacing
                    times[0] = -1e-3
                for t in times:
                    extra += 1
                    name = f"x-{t:f}-{extra}.end"
                    (self.path / name).write_bytes(b"\n")  # an empty file ends playback
                    names.append(name)
            for i, e in enumerate(self.entries):
                rest = e.name[_NAME.match(e.name).end() :]
                staged = f"{e.type}-{e.time_text}-{i}{rest}"
                os.symlink(self.source / e.name, self.path / staged)
                names.append(staged)
            if self.entries:
                last = max(e.time for e in self.entries)
                sentinel = f"x-{last + SENTINEL_DELAY_S:f}-{extra + 1}.end"
                (self.path / sentinel).write_bytes(b"\n")
                names.append(sentinel)
            (self.path / "INDEX.txt").write_text("".join(n + "\n" for n in names))
        except BaseException:
            shutil.rmtree(self.path, ignore_errors=True)
            raise

    def close(self) -> None:
        shutil.rmtree(self.path, ignore_errors=True)


def fake_libfreenect() -> Path:
    """Debian's fake libfreenect (what the `fakenect` wrapper puts first on the library
    path): found from the wrapper script, else in the multiarch library folder."""
    dirs: list[Path] = []
    wrapper = shutil.which("fakenect")
    if wrapper:
        try:
            text = Path(wrapper).read_text(errors="replace")
        except OSError:
            text = ""
        dirs += [Path(m) for m in re.findall(r'LIBRARY_PATH="?([^":$]*fakenect)/?:', text)]
    multiarch = sysconfig.get_config_var("MULTIARCH") or ""
    for base in ("/usr/lib", "/usr/local/lib"):
        if multiarch:
            dirs.append(Path(base) / multiarch / "fakenect")
        dirs.append(Path(base) / "fakenect")
    for d in dirs:
        for name in ("libfreenect.so.0.5", "libfreenect.so", "libfreenect.so.0"):
            if (d / name).is_file():
                return d / name
        found = sorted(d.glob("libfreenect.so*")) if d.is_dir() else []
        if found:
            return found[0]
    raise FakenectError(
        "fakenect's fake libfreenect not found: apt-get install libfreenect-bin libfreenect-dev "
        "(make system-deps)"
    )


# libfreenect's registration helper, as src/registration.c defines it: world x, y of a
# 640×480 depth pixel at depth wz scale with 2·ref_pix_size·wz / ref_distance about the
# image centre (320, 240). A replayed recording has no registration data of the device,
# so the ratio is a 640×480 pinhole's of 57° horizontal field of view (the calibration's
# default Kinect): ref_distance / (2·ref_pix_size) = 320 / tan(28.5°) pixels.
SHIM_SOURCE = r"""
/* walker-slam: freenect_camera_to_world for Debian's fake libfreenect (generated). */
struct _freenect_device;

void freenect_camera_to_world(struct _freenect_device *dev, int cx, int cy, int wz,
                              double *wx, double *wy)
{
    const double focal_px = 589.3667;  /* 320 / tan(28.5 deg) */
    double factor = (double)wz / focal_px;
    (void)dev;
    *wx = (double)(cx - 320) * factor;
    *wy = (double)(cy - 240) * factor;
}
"""


def cache_dir() -> Path:
    base = os.environ.get("XDG_CACHE_HOME") or str(Path.home() / ".cache")
    return Path(base) / "walker-slam"


def fakenect_shim() -> Path:
    """The compiled `freenect_camera_to_world` shim, built on first use (needs cc)."""
    cc = os.environ.get("CC") or shutil.which("cc") or shutil.which("gcc")
    if not cc:
        raise FakenectError(
            "fakenect replay needs a C compiler to build its shim: apt-get install gcc"
        )
    digest = hashlib.sha256((SHIM_SOURCE + cc).encode()).hexdigest()[:16]
    out = cache_dir() / f"fakenect-shim-{digest}.so"
    if out.is_file():
        return out
    out.parent.mkdir(parents=True, exist_ok=True)
    with tempfile.TemporaryDirectory(dir=out.parent) as tmp:
        src = Path(tmp) / "fakenect_shim.c"
        src.write_text(SHIM_SOURCE)
        lib = Path(tmp) / out.name
        run = subprocess.run(
            [*cc.split(), "-shared", "-fPIC", "-O2", "-o", str(lib), str(src)],
            capture_output=True,
            text=True,
        )
        if run.returncode != 0:
            detail = (run.stderr.strip().splitlines() or ["no output"])[-1]
            raise FakenectError(f"building the fakenect shim with {cc} failed: {detail}")
        os.replace(lib, out)  # atomic: concurrent first uses agree
    return out


def replay_environment(staged: Path, base: dict[str, str] | None = None) -> dict[str, str]:
    """Environment of a process that replays `staged` through the sync API."""
    env = dict(os.environ if base is None else base)
    preload = [str(fake_libfreenect()), str(fakenect_shim())]
    if env.get("LD_PRELOAD"):
        preload.append(env["LD_PRELOAD"])
    env["LD_PRELOAD"] = ":".join(preload)
    env["FAKENECT_PATH"] = str(staged)
    return env
