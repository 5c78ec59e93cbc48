"""TMF8828 driver on any object with smbus2.SMBus's methods (a real bus or the emulator's).

:class:`TMF8828` talks to one device: power-up, image download through the bootloader,
mode and config page, start and stop, and interrupt-driven readout of raw histogram
packets and result records, reassembled into 128-bin histograms per zone plus the
reference channel. :class:`TMF8828Array` runs several sensors on one bus (enable pins or
an I2C multiplexer), measured in turn so they do not blind each other.

Robustness: every transfer is retried on ``OSError`` (NACK, timeout) within
``max_retries``; a record whose header does not check is read again; a repeated packet
(same TID) is dropped; a lost packet, a wrong CID that does not go away or a sensor reset
breaks the capture, which is discarded and measured again. Everything is counted in
:class:`ErrorCounts`. A frame is returned only when every packet of every sub-capture of
every sensor arrived in order: a frame that is not whole is never returned as whole.
"""

from __future__ import annotations

import errno
from dataclasses import dataclass, field
from typing import Any, Callable

import numpy as np
from smbus2 import i2c_msg

from ..errors import UserError
from . import protocol as P
from .bus import RealClock

__all__ = [
    "CaptureBroken",
    "DeviceError",
    "DriverOptions",
    "ErrorCounts",
    "Frame",
    "FrameDropped",
    "SensorLost",
    "SensorSpec",
    "TMF8828",
    "TMF8828Array",
    "bus_limited_frame_s",
]


class DeviceError(UserError):
    """The device does not behave (no answer, bootloader refuses the image, command errors)."""


class SensorLost(Exception):
    """The sensor stopped answering as the application (reset, power glitch): re-initialise it."""


class CaptureBroken(Exception):
    """A capture was not whole (lost packet, unreadable record): discard it."""


class FrameDropped(Exception):
    """No whole frame could be read within the retry limits; the frame is skipped (counted)."""


ERROR_KINDS = ("i2c", "timeout", "corrupt", "wrong_cid", "repeat", "skip", "incomplete", "reset", "frames_dropped")


@dataclass
class ErrorCounts:
    """What went wrong and was handled, by kind (see ``docs/acquisition.md``)."""

    counts: dict[str, int] = field(default_factory=lambda: dict.fromkeys(ERROR_KINDS, 0))

    def add(self, kind: str, n: int = 1) -> None:
        self.counts[kind] = self.counts.get(kind, 0) + n

    def __getitem__(self, kind: str) -> int:
        return self.counts.get(kind, 0)

    def total(self) -> int:
        return sum(self.counts.values())

    def short(self) -> str:
        nz = {k: v for k, v in self.counts.items() if v}
        return ", ".join(f"{k} {v}" for k, v in nz.items()) if nz else "none"


@dataclass(frozen=True)
class DriverOptions:
    """How the driver configures and reads a sensor.

    - ``layout``: TMF8828 zone layout ("3x3", "3x6", "4x4", "8x8").
    - ``period_ms``, ``kilo_iterations``: config page (period per result record; iterations x1024).
    - ``spad_map``: SPAD map id (``None``: the layout's default, see ``protocol.SPAD_MAPS``).
    - ``max_retries``: attempts per transfer after an ``OSError``, and reads per bad record.
    - ``max_broken``: broken captures per sensor and frame before the frame is dropped.
    - ``poll_s``: interval between INT_STATUS polls while waiting.
    - ``record_timeout_s``: longest wait for a record beyond the measurement period.
    """

    layout: str = "3x3"
    period_ms: int = P.DEFAULT_PERIOD_MS
    kilo_iterations: int = 244
    spad_map: int | None = None
    max_retries: int = 5
    max_broken: int = 4
    poll_s: float = 200e-6
    record_timeout_s: float = 0.1

    def __post_init__(self):
        if self.layout not in P.LAYOUTS:
            raise UserError(f"layout: must be one of {', '.join(P.LAYOUTS)}, got {self.layout!r}")
        if not 1 <= self.period_ms <= 0xFFFF:
            raise UserError(f"period_ms: must be in [1, 65535], got {self.period_ms}")
        if not 1 <= self.kilo_iterations <= 0xFFFF:
            raise UserError(f"kilo_iterations: must be in [1, 65535], got {self.kilo_iterations}")
        if self.spad_map is not None and not 1 <= self.spad_map <= 255:
            raise UserError(f"spad_map: must be in [1, 255], got {self.spad_map}")
        if self.layout == "8x8" and self.spad_map not in (None, P.SPAD_MAP_8X8):
            raise UserError(f"spad_map: 8x8 mode needs SPAD map {P.SPAD_MAP_8X8}, got {self.spad_map}")

    @property
    def spad_map_id(self) -> int:
        return P.DEFAULT_SPAD_MAP[self.layout] if self.spad_map is None else self.spad_map


@dataclass
class SensorData:
    """One sensor's whole frame: counts per TMF zone index, the reference, the result records."""

    zones: np.ndarray  # (n_index, 128) int64, indexed by TMF zone index
    reference: np.ndarray  # (128,) float: mean over configurations and sub-captures
    results: list[P.Result]


class TMF8828:
    """One TMF8828 at ``address`` on ``bus`` (anything with smbus2.SMBus's methods)."""

    def __init__(self, bus: Any, address: int = P.ADDRESS, *, options: DriverOptions = DriverOptions(),
                 clock=None, errors: ErrorCounts | None = None, name: str = "tmf8828", int_pin: Any = None):
        self.bus = bus
        #: the INT line as an input whose ``value`` is 1 while asserted (gpiozero ``DigitalInputDevice``
        #: with ``pull_up=True``: INT is active-low, open-drain); ``None``: poll INT_STATUS over I2C
        self.int_pin = int_pin
        self.address = address
        self.options = options
        self.layout = P.Layout(options.layout)
        self.clock = clock or getattr(bus, "clock", None) or RealClock()
        self.errors = errors if errors is not None else ErrorCounts()
        self.name = name
        self.last_tid: int | None = None
        self.running = False

    # ---- transfers with retries ---------------------------------------------------------
    def _retry(self, fn: Callable, *args):
        n = self.options.max_retries
        for attempt in range(n + 1):
            try:
                return fn(*args)
            except OSError as e:
                self.errors.add("timeout" if e.errno == errno.ETIMEDOUT else "i2c")
                if attempt == n:
                    raise SensorLost(f"{self.name}: {n + 1} failed transfers in a row at {self.address:#04x}: {e}") from e
                self.clock.sleep(self.options.poll_s * (attempt + 1))

    def _probe(self, reg: int) -> int | None:
        """Read without retries or counting: for waits where silence is expected (reboot, address move)."""
        try:
            return self.bus.read_byte_data(self.address, reg)
        except OSError:
            return None

    def read(self, reg: int) -> int:
        return self._retry(self.bus.read_byte_data, self.address, reg)

    def write(self, reg: int, value: int) -> None:
        self._retry(self.bus.write_byte_data, self.address, reg, value)

    def read_block(self, reg: int, n: int) -> bytes:
        """``n`` bytes from ``reg``: an SMBus block read up to 32 bytes, ``i2c_rdwr`` beyond."""
        if n <= 32:
            return bytes(self._retry(self.bus.read_i2c_block_data, self.address, reg, n))

        def rdwr():
            w, r = i2c_msg.write(self.address, [reg]), i2c_msg.read(self.address, n)
            self.bus.i2c_rdwr(w, r)
            return bytes(r)

        return self._retry(rdwr)

    def write_block(self, reg: int, data: bytes) -> None:
        if len(data) <= 32:
            self._retry(self.bus.write_i2c_block_data, self.address, reg, list(data))
        else:
            self._retry(lambda: self.bus.i2c_rdwr(i2c_msg.write(self.address, bytes([reg]) + bytes(data))))

    def _wait(self, cond: Callable[[], bool], timeout_s: float, what: str, tolerate_oserror: bool = False) -> None:
        deadline = self.clock.now() + timeout_s
        while True:
            try:
                if cond():
                    return
            except (OSError, SensorLost):
                if not tolerate_oserror:
                    raise
            if self.clock.now() > deadline:
                raise DeviceError(f"{self.name}: timed out after {timeout_s * 1e3:.0f} ms waiting for {what}")
            self.clock.sleep(self.options.poll_s)

    # ---- power-up and image -------------------------------------------------------------
    def power_up(self, timeout_s: float = 0.05) -> None:
        """PON and wait for cpu_ready (the enable pin is high, or the device has none)."""
        en = self.read(P.ENABLE)
        if not en & P.ENABLE_CPU_READY:
            self.write(P.ENABLE, en | P.ENABLE_PON)
            self._wait(lambda: self.read(P.ENABLE) & P.ENABLE_CPU_READY, timeout_s, "cpu_ready (ENABLE bit 6)")

    def app_id(self) -> int:
        return self.read(P.APPID)

    def _bl_command(self, cmd: int, payload: bytes = b"", timeout_s: float = 0.02) -> None:
        frame = P.bl_frame(cmd, payload)
        for attempt in range(self.options.max_retries + 1):
            self.write_block(P.BL_CMD_STAT, frame)  # one I2C write per frame
            status = b""

            def done():
                nonlocal status
                status = self.read_block(P.BL_CMD_STAT, 3)
                return status[0] < P.BL_BUSY_MIN

            self._wait(done, timeout_s, f"bootloader command {cmd:#04x}")
            if status == P.BL_OK:
                return
            if status[0] in (P.BL_CSUM_ERROR, P.BL_SIZE_ERROR) and attempt < self.options.max_retries:
                self.errors.add("corrupt")  # the frame arrived damaged: send it again
                continue
            raise DeviceError(f"{self.name}: bootloader command {cmd:#04x} failed with status {status.hex()}")

    def download(self, image: bytes) -> None:
        """Download the application image through the bootloader and start it."""
        appid = self.app_id()
        if appid != P.APPID_BOOTLOADER:
            raise DeviceError(f"{self.name}: APPID is {appid:#04x}, expected the bootloader ({P.APPID_BOOTLOADER:#04x})")
        self._bl_command(P.BL_DOWNLOAD_INIT, bytes([P.BL_DOWNLOAD_INIT_SEED]))
        self._bl_command(P.BL_ADDR_RAM, bytes([0, 0]))
        for off in range(0, len(image), P.BL_MAX_PAYLOAD):
            self._bl_command(P.BL_W_RAM, image[off : off + P.BL_MAX_PAYLOAD])
        self.write_block(P.BL_CMD_STAT, P.bl_frame(P.BL_RAMREMAP_RESET))  # no reply
        self.clock.sleep(3e-3)
        try:
            self._wait(lambda: self._probe(P.APPID) == P.APPID_APP, 0.05, "the application (APPID 0x03)")
        except DeviceError:
            raise DeviceError(
                f"{self.name}: the device did not start the application after the download: is the image "
                "the TMF8828 application (and, with --emulate, the synthetic one)?"
            ) from None

    # ---- commands and config ------------------------------------------------------------
    def command(self, code: int, timeout_s: float = 0.04, ok=(P.STAT_OK,)) -> int:
        self.write(P.CMD_STAT, code)
        stat = 0

        def done():
            nonlocal stat
            stat = self.read(P.CMD_STAT)
            return stat < P.STAT_PENDING_MIN

        self._wait(done, timeout_s, f"command {code:#04x}")
        if stat not in ok:
            raise DeviceError(f"{self.name}: command {code:#04x} answered status {stat:#04x}")
        return stat

    def wait_idle(self, timeout_s: float = 0.1) -> None:
        """Wait until no command is pending (e.g. a stop sent without waiting)."""
        self._wait(lambda: self.read(P.CMD_STAT) < P.STAT_PENDING_MIN, timeout_s, "the previous command")

    def _load_page(self) -> None:
        self.command(P.CMD_LOAD_CONFIG_PAGE)
        cid = self.read(P.CID_RID)
        if cid != P.CID_CONFIG:
            raise DeviceError(f"{self.name}: config page load mapped CID {cid:#04x}, expected {P.CID_CONFIG:#04x}")

    def configure(self) -> None:
        """Mode, config page (period, iterations, SPAD map, raw histogram dump on), interrupts."""
        o = self.options
        want = self.layout.mode_register
        if self.read(P.MODE) != want:
            self.command(P.CMD_MODE_8X8 if self.layout.is_8x8 else P.CMD_MODE_LEGACY)
        self._load_page()
        self.write_block(P.CFG_PERIOD_MS, o.period_ms.to_bytes(2, "little") + o.kilo_iterations.to_bytes(2, "little"))
        self.write(P.CFG_SPAD_MAP, o.spad_map_id)
        self.write(P.CFG_HIST_DUMP, P.HIST_DUMP_RAW)
        self.command(P.CMD_WRITE_CONFIG_PAGE)
        # read it back: a page that did not take is a configuration we would mislabel
        self._load_page()
        page = self.read_block(P.CFG_PERIOD_MS, 4)
        if page != o.period_ms.to_bytes(2, "little") + o.kilo_iterations.to_bytes(2, "little") or \
                self.read(P.CFG_SPAD_MAP) != o.spad_map_id or not self.read(P.CFG_HIST_DUMP) & P.HIST_DUMP_RAW:
            raise DeviceError(f"{self.name}: the config page did not keep the values written")
        self.write(P.INT_ENAB, P.INT_RESULT | P.INT_HISTOGRAM)
        self.write(P.INT_STATUS, 0xFF)

    def set_address(self, new: int) -> None:
        """Move the device to I2C address ``new`` (config page 0x3B, command 0x21)."""
        self._load_page()
        self.write(P.CFG_I2C_ADDRESS, new << 1)
        self.command(P.CMD_WRITE_CONFIG_PAGE)
        self.write(P.CMD_STAT, P.CMD_I2C_ADDRESS)
        self.address = new

        def moved():
            stat = self._probe(P.CMD_STAT)  # silence while it moves is expected
            return stat is not None and stat < P.STAT_PENDING_MIN

        self._wait(moved, 0.05, f"the move to address {new:#04x}")

    def start(self) -> None:
        self.wait_idle()
        self.write(P.INT_STATUS, 0xFF)
        self.command(P.CMD_MEASURE, ok=(P.STAT_ACCEPTED, P.STAT_OK))
        self.last_tid = None
        self.running = True

    def stop(self, wait: bool = False) -> None:
        """Stop measuring; with ``wait=False`` the stop completes while the host goes on."""
        self.running = False
        self.write(P.CMD_STAT, P.CMD_STOP)
        if wait:
            self.wait_idle()

    def init(self, image: bytes) -> None:
        """Power-up, download, configure: what a sensor needs after every power cycle.

        A sensor whose application already runs (no enable line, a previous session did not
        power it down) is stopped and configured again without a download."""
        self.power_up()
        if self.app_id() == P.APPID_APP:
            self.wait_idle()  # a command still running would make the device ignore the stop
            self.write(P.CMD_STAT, P.CMD_STOP)
            self.wait_idle()
        else:
            self.download(image)
        self.configure()

    # ---- readout ------------------------------------------------------------------------
    def _record_ok(self, kind: int, data: bytes) -> bool:
        if kind == P.INT_RESULT:
            return data[0] == P.CID_RESULT and (data[2] | data[3] << 8) == P.RESULT_SIZE_FIELD
        return (data[0] == P.CID_HISTOGRAM and (data[2] | data[3] << 8) == P.HIST_SIZE_FIELD
                and data[4] < P.PACKETS_PER_CONFIG and data[5] == P.HIST_PAYLOAD and data[6] < self.layout.n_configs)

    def _read_record(self, kind: int) -> bytes:
        n = P.HIST_PACKET_LEN if kind == P.INT_HISTOGRAM else P.RESULT_LEN
        want_cid = P.CID_HISTOGRAM if kind == P.INT_HISTOGRAM else P.CID_RESULT
        for _ in range(self.options.max_retries + 1):
            data = self.read_block(P.CID_RID, n)
            if self._record_ok(kind, data):
                return data
            self.errors.add("wrong_cid" if data[0] != want_cid else "corrupt")
        raise CaptureBroken(f"{self.name}: a record did not check after {self.options.max_retries + 1} reads")

    def _next_record(self) -> tuple[int, bytes]:
        """Wait for the next offered record (interrupt-driven) and read it; not yet cleared."""
        timeout = self.layout.n_subcaptures * self.options.period_ms * 1e-3 + self.options.record_timeout_s
        deadline = self.clock.now() + timeout
        while True:
            if self.int_pin is not None and not self.int_pin.value:
                # wait on the INT line: no bus traffic until the device raises it
                if self.clock.now() > deadline:
                    self._check_alive()
                    raise CaptureBroken(f"{self.name}: no interrupt within {timeout * 1e3:.0f} ms")
                self.clock.sleep(self.options.poll_s)
                continue
            st = self.read(P.INT_STATUS)
            if st & P.INT_HISTOGRAM:
                kind = P.INT_HISTOGRAM
                break
            if st & P.INT_RESULT:
                kind = P.INT_RESULT
                break
            if self.clock.now() > deadline:
                self._check_alive()
                raise CaptureBroken(f"{self.name}: no record within {timeout * 1e3:.0f} ms")
            self.clock.sleep(self.options.poll_s)
        try:
            return kind, self._read_record(kind)
        except CaptureBroken:
            self.clear(kind)
            raise

    def _check_alive(self) -> None:
        try:
            appid = self.read(P.APPID)
        except SensorLost:
            raise SensorLost(f"{self.name}: does not answer at {self.address:#04x}") from None
        if appid != P.APPID_APP:
            raise SensorLost(f"{self.name}: APPID reads {appid:#04x}: the device has reset")

    def clear(self, kind: int) -> None:
        self.write(P.INT_STATUS, kind)

    def read_subcapture(self) -> tuple[np.ndarray, P.Result]:
        """One sub-capture: (configs, 10 channels, 128) counts and its result record.

        Raises :class:`CaptureBroken` if any packet is missing or out of order."""
        K = self.layout.n_configs
        n_packets = P.PACKETS_PER_CONFIG * K
        pk = np.empty((K, P.PACKETS_PER_CONFIG, P.N_BINS), np.uint8)
        idx, broken, last = 0, False, None
        while True:
            kind, data = self._next_record()
            if kind == P.INT_RESULT:
                self.clear(kind)
                res = P.parse_result(data)
                self.last_tid = res.tid
                if broken or idx != n_packets:
                    self.errors.add("incomplete")
                    raise CaptureBroken(f"{self.name}: capture with {idx} of {n_packets} packets in order")
                counts = pk.astype(np.int64).reshape(K, P.N_PLANES, P.N_CHANNELS, P.N_BINS)
                return counts[:, 0] | (counts[:, 1] << 8) | (counts[:, 2] << 16), res
            for reread in (False, True):
                head = (data[1], data[6], data[4])  # tid, config, number
                exp = divmod(idx, P.PACKETS_PER_CONFIG)
                if head[0] != self.last_tid and head[1:] == exp:
                    verdict = "ok"
                elif last is not None and head == last:
                    verdict = "repeat"
                else:
                    verdict = "skip"
                if reread and verdict != "skip":
                    self.errors.add("corrupt")  # the first read's header had a bit error
                if verdict != "skip" or reread:
                    break
                data = self._read_record(kind)  # a bit error or a real skip? read it again
            if verdict == "ok":
                pk[exp[0], exp[1]] = np.frombuffer(data, np.uint8, P.HIST_PAYLOAD, 7)
                idx += 1
            elif verdict == "repeat":
                self.errors.add("repeat")
            elif not broken:
                self.errors.add("skip")
                broken = True
            self.last_tid, last = head[0], head
            self.clear(kind)

    def read_frame(self) -> SensorData:
        """All sub-captures of one frame (4 in 8x8), in order, each whole; retried within limits."""
        lay = self.layout
        zones = np.zeros((64 if lay.is_8x8 else 18, P.N_BINS), np.int64)
        ref = np.zeros(P.N_BINS)
        results: list[P.Result] = []
        broken = 0
        s_next = 0
        while s_next < lay.n_subcaptures:
            try:
                counts, res = self.read_subcapture()
            except CaptureBroken:
                broken += 1
                if broken > self.options.max_broken:
                    raise FrameDropped(f"{self.name}: {broken} broken captures in one frame") from None
                s_next, results, ref = 0, [], np.zeros(P.N_BINS)
                continue
            s = res.subcapture if lay.is_8x8 else 0
            if s != s_next:
                # joined mid-frame (continuous mode) or a sub-capture was lost: start over at 0
                if s_next:
                    self.errors.add("incomplete")
                s_next, results, ref = 0, [], np.zeros(P.N_BINS)
                if s != 0:
                    continue
            for k in range(lay.n_configs):
                for c in lay.channels:
                    zones[lay.zone_index(s, k, c)] = counts[k, c]
                ref += counts[k, 0]
            results.append(res)
            s_next += 1
        return SensorData(zones, ref / (lay.n_configs * lay.n_subcaptures), results)


@dataclass(frozen=True)
class SensorSpec:
    """One sensor of an array: how to reach it and where its scene zones are.

    - ``address``: its I2C address once running (enable-pin rigs move each sensor off 0x41).
    - ``pin``: an output with ``on()``/``off()`` driving its enable line, or ``None``.
    - ``mux_channel``: its channel on the multiplexer, or ``None``.
    - ``zone_map``: TMF zone index of each scene zone.
    - ``int_pin``: its INT line as an input (``value`` 1 while asserted), or ``None`` to poll INT_STATUS.
    """

    name: str
    zone_map: tuple[int, ...]
    address: int = P.ADDRESS
    pin: Any = None
    mux_channel: int | None = None
    int_pin: Any = None


@dataclass
class Frame:
    """A whole frame of the array: (sensors, zones, 128) counts, (sensors, 128) reference, host time."""

    histograms: np.ndarray
    reference: np.ndarray
    timestamp: float
    results: list[list[P.Result]]


class TMF8828Array:
    """Several TMF8828 on one bus, selected by enable pins or an I2C mux, measured in turn.

    With one sensor it measures continuously (start once, read frame after frame); with
    several, each frame starts, reads and stops each sensor in turn.
    """

    def __init__(self, bus: Any, sensors: list[SensorSpec], image: bytes, *, options: DriverOptions = DriverOptions(),
                 mux_address: int | None = None, clock=None, max_recoveries: int = 3):
        if not sensors:
            raise UserError("a rig needs at least one sensor")
        self.bus = bus
        self.specs = list(sensors)
        self.image = bytes(image)
        self.options = options
        self.mux_address = mux_address
        self.clock = clock or getattr(bus, "clock", None) or RealClock()
        self.errors = ErrorCounts()
        self.max_recoveries = max_recoveries
        self.devices = [
            TMF8828(bus, P.ADDRESS, options=options, clock=self.clock, errors=self.errors, name=s.name,
                    int_pin=s.int_pin)
            for s in self.specs
        ]
        self.continuous = len(self.specs) == 1
        self._selected: int | None = None

    # ---- selection ----------------------------------------------------------------------
    def _select(self, i: int, force: bool = False) -> None:
        spec = self.specs[i]
        if spec.mux_channel is None or self.mux_address is None or (self._selected == i and not force):
            return
        dev = self.devices[i]
        dev._retry(self.bus.write_byte, self.mux_address, 1 << spec.mux_channel)
        self._selected = i

    def _bring_up(self, i: int) -> None:
        spec, dev = self.specs[i], self.devices[i]
        if spec.pin is not None:
            spec.pin.off()
            self.clock.sleep(1e-3)
            spec.pin.on()
            self.clock.sleep(1e-3)  # the page: wait ~1 ms after the enable pin goes high
        self._select(i, force=True)
        dev.address = P.ADDRESS
        dev.init(self.image)
        if spec.address != P.ADDRESS:
            dev.set_address(spec.address)
        if self.continuous:
            dev.start()

    def open(self) -> "TMF8828Array":
        """Bring every sensor up: with enable pins one at a time (each then moved to its own address)."""
        for spec in self.specs:
            if spec.pin is not None:
                spec.pin.off()
        for i, spec in enumerate(self.specs):
            try:
                self._bring_up(i)
            except SensorLost as e:
                where = f" on mux channel {spec.mux_channel}" if spec.mux_channel is not None else ""
                raise DeviceError(f"{spec.name}: no answer{where} ({e}); check power, wiring and the enable line") from None
        return self

    def close(self) -> None:
        for i, dev in enumerate(self.devices):
            try:
                self._select(i)
                dev.stop()
            except (OSError, SensorLost, DeviceError):
                pass

    def __enter__(self):
        return self.open()

    def __exit__(self, *exc):
        self.close()

    # ---- frames -------------------------------------------------------------------------
    def _recover(self, i: int) -> None:
        self.errors.add("reset")
        for _ in range(self.max_recoveries):
            try:
                self._bring_up(i)
                return
            except (SensorLost, DeviceError):
                continue
        raise DeviceError(f"{self.specs[i].name}: could not bring the sensor back after a reset")

    def _read_sensor(self, i: int) -> SensorData:
        dev = self.devices[i]
        for _ in range(self.max_recoveries + 1):
            try:
                self._select(i)
                if not self.continuous:
                    dev.start()
                try:
                    return dev.read_frame()
                finally:
                    if not self.continuous:
                        dev.stop()
            except (SensorLost, DeviceError):
                self._recover(i)
        raise FrameDropped(f"{self.specs[i].name}: lost again after {self.max_recoveries} recoveries")

    def read_frame(self) -> Frame:
        """One whole frame of every sensor. Raises :class:`FrameDropped` (counted) if one was not whole."""
        hists, refs, results = [], [], []
        try:
            for i, spec in enumerate(self.specs):
                d = self._read_sensor(i)
                hists.append(d.zones[np.asarray(spec.zone_map)])
                refs.append(d.reference)
                results.append(d.results)
        except FrameDropped:
            self.errors.add("frames_dropped")
            raise
        return Frame(np.stack(hists).astype(np.float64), np.stack(refs), self.clock.now(), results)


def bus_limited_frame_s(layout: str, n_sensors: int, frequency_hz: float, *, continuous: bool | None = None,
                        mux: bool = False) -> float:
    """The least bus time one frame takes with this driver's transfers, with no waiting at all.

    Per record: one INT_STATUS read (39 bits), the record read through ``i2c_rdwr`` (30 + 9 n
    bits for n bytes) and the interrupt clear (29 bits). Measured in turn (several sensors),
    each sensor also costs its start (idle check, clear, measure command and one status read),
    its stop, and with a mux one channel select. Bits include start, address, ACK and stop bits.
    """
    lay = P.Layout(layout)
    continuous = n_sensors == 1 if continuous is None else continuous
    read_byte, write_byte = 39, 29
    per_packet = read_byte + (30 + 9 * P.HIST_PACKET_LEN) + write_byte
    per_result = read_byte + (30 + 9 * P.RESULT_LEN) + write_byte
    per_sensor = lay.n_subcaptures * (lay.packets_per_subcapture * per_packet + per_result)
    if not continuous:
        per_sensor += read_byte + write_byte + write_byte + read_byte + write_byte + (20 if mux else 0)
    return n_sensors * per_sensor / frequency_hz
