"""A register-level TMF8828 emulator whose histograms come from tofjax's forward model.

It answers the byte-level transfers of :class:`~tofjax.hw.bus.SimBus` as the protocol
page (``../shared/tmf8828-protocol.md``) describes the device: power-up and cpu_ready,
the bootloader (frames with checksums, status bytes, RAM download, remap-reset into the
application), the application registers, commands with pending/ok/error replies, the
common config page, the I2C address change, interrupts, raw histogram packets offered one
at a time until their interrupt bit is cleared, and the result record. Time comes from a
shared :class:`~tofjax.hw.bus.SimClock`.

Device faults (repeated or lost packets, wrong CIDs, resets) are injected here; bus faults
(NACKs, timeouts, bit errors) in :class:`~tofjax.hw.bus.SimBus`.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from . import protocol as P
from .bus import SimClock

__all__ = ["DeviceFaults", "EmulatorTiming", "TMF8828Emulator", "default_zone_map"]

SPEED_OF_LIGHT = 299_792_458.0


@dataclass(frozen=True)
class DeviceFaults:
    """Device faults, as probabilities (deterministic for a given seed).

    - ``repeat``: per histogram packet: after its interrupt is cleared it is offered again, same TID.
    - ``skip``: per histogram packet: the next packet is lost (the TID jumps over it).
    - ``wrong_cid``: per record read: the read shows a CID that is not the record's.
    - ``reset``: per record: the device resets when the host clears the record (back to the
      bootloader at 0x41, the application lost), i.e. mid-frame.
    """

    repeat: float = 0.0
    skip: float = 0.0
    wrong_cid: float = 0.0
    reset: float = 0.0
    seed: int = 0


@dataclass(frozen=True)
class EmulatorTiming:
    """Device latencies (seconds). The command times are the protocol page's typical values;
    ``cpu_ready_s``, ``bl_command_s``, ``mode_switch_s`` and ``address_s`` are NOT on the page
    (chosen small and plausible)."""

    cpu_ready_s: float = 0.5e-3
    bl_command_s: float = 20e-6
    app_boot_s: float = 4e-3
    page_s: float = 3e-3
    mode_switch_s: float = 3e-3
    measure_s: float = 5e-3
    stop_s: float = 25e-3
    address_s: float = 1e-3
    factory_calibration_s: float = 1.0


def default_zone_map(layout: P.Layout, zones: int) -> list[int]:
    """Scene zone ``z`` -> TMF zone index: the first ``zones`` zones of the layout in index order
    (legacy: configuration 0's channels 1..9, then configuration 1's; 8x8: row-major)."""
    idx = [layout.zone_index(*slot) for slot in layout.slots()]
    if zones > len(idx):
        raise ValueError(f"{zones} zones do not fit layout {layout.name} ({len(idx)} zones)")
    return idx[:zones]


@dataclass
class _Record:
    kind: int  # INT_HISTOGRAM or INT_RESULT
    data: bytearray


@dataclass
class _Cmd:
    code: int
    done_at: float
    reply: int = P.STAT_OK


class TMF8828Emulator:
    """One emulated TMF8828.

    **Arguments:**

    - ``expected``: (zones, 128) expected counts of this sensor's scene zones (the forward model).
    - ``reference``: (128,) expected counts of the reference SPAD (the instrument response).
    - ``clock``: the shared simulated clock.
    - ``noise``: Poisson photon noise on each frame (off: the expected counts, rounded).
    - ``zone_map``: scene zone -> TMF zone index, per layout name (default :func:`default_zone_map`).
    - ``image``: the only application image this emulator runs (default the synthetic one).
    - ``bin_width_s``: for the distances in the result record.
    - ``faults``, ``timing``, ``seed``: see :class:`DeviceFaults`, :class:`EmulatorTiming`.
    """

    def __init__(self, expected, reference, clock: SimClock, *, noise: bool = True,
                 zone_map: dict[str, list[int]] | None = None, image: bytes | None = None,
                 bin_width_s: float = 1e-10, faults: DeviceFaults = DeviceFaults(),
                 timing: EmulatorTiming = EmulatorTiming(), seed: int = 0, name: str = "tmf8828"):
        self.expected = np.asarray(expected, np.float64)
        self.reference = np.asarray(reference, np.float64)
        if self.expected.ndim != 2 or self.expected.shape[1] != P.N_BINS or self.reference.shape != (P.N_BINS,):
            raise ValueError(f"expected must be (zones, {P.N_BINS}) and reference ({P.N_BINS},)")
        self.clock = clock
        self.noise = noise
        self.zone_map = dict(zone_map or {})
        self.image = P.synthetic_image() if image is None else bytes(image)
        self.bin_width_s = bin_width_s
        self.faults = faults
        self.timing = timing
        self.name = name
        self._rng = np.random.default_rng(seed)
        self._frng = np.random.default_rng(faults.seed + 7919 * (seed + 1))
        #: one-shot device faults ("repeat", "skip", "wrong_cid", "reset") fired at the next chance
        self.armed: list[str] = []
        self.counts = {"frames": 0, "records": 0, "resets": 0}
        self.last_frame: tuple[np.ndarray, np.ndarray] | None = None
        self.enabled = False
        self._power_off()

    @classmethod
    def from_sensor_model(cls, model, distance_m: float, clock: SimClock, **kwargs) -> "TMF8828Emulator":
        """An emulator whose histograms come from a sensor model fitted on real data
        (``tofjax sensor fit``): a TMF882x looking at a flat target at ``distance_m``, with the
        learned pulse, pile-up and the reference channel's own pulse."""
        from ..sensor.simulate import emulator_signals

        lam, ref = emulator_signals(model, distance_m)
        return cls(lam[0], ref[0], clock, bin_width_s=float(model.bin_width_s), **kwargs)

    # ---- power --------------------------------------------------------------------------
    def _power_off(self) -> None:
        self.address = P.ADDRESS
        self.regs = bytearray(256)
        self.ptr = 0
        self.pon = False
        self.cpu_ready_at: float | None = None
        self.app = False
        self.booting_until: float | None = None
        self.ram = bytearray(0x10000)
        self.ram_ptr = 0
        self.ram_written = 0
        self.bl_inited = False
        self.bl_busy_until = 0.0
        self._bl_pending_ok = False
        self._boot_ok = False
        self._bl_status(0x00)
        self._reset_app_state()

    def _reset_app_state(self) -> None:
        self.mode = P.MODE_LEGACY
        self.config = bytearray(256)
        self._default_config()
        self.cmd: _Cmd | None = None
        self.int_status = 0
        self.int_enab = 0
        self.measuring = False
        self.queue: list[_Record] = []
        self.offered: _Record | None = None
        self.tid = 0
        self.next_handover = 0.0
        self.drained_at = 0.0
        self.sub = 0
        self.result_number = 0
        self.frame_counts: tuple[np.ndarray, np.ndarray] | None = None

    def _default_config(self) -> None:
        c = self.config
        c[P.CFG_PERIOD_MS : P.CFG_PERIOD_MS + 2] = P.DEFAULT_PERIOD_MS.to_bytes(2, "little")
        # NOT ON THE PROTOCOL PAGE: the default kilo-iterations (the public drivers' 537).
        c[P.CFG_KILO_ITERATIONS : P.CFG_KILO_ITERATIONS + 2] = (537).to_bytes(2, "little")
        c[P.CFG_CONFIDENCE] = 6
        c[P.CFG_SPAD_MAP] = P.SPAD_MAP_8X8 if self.mode == P.MODE_8X8 else P.DEFAULT_SPAD_MAP["3x3"]
        c[P.CFG_HIST_DUMP] = 0
        c[P.CFG_I2C_ADDRESS] = P.ADDRESS << 1

    def set_enable(self, high: bool) -> None:
        """The enable pin. Low: everything is lost (RAM, address); high: the device answers at 0x41."""
        if high and not self.enabled:
            self._power_off()
        if not high:
            self._power_off()
        self.enabled = bool(high)

    def _reset_to_bootloader(self) -> None:
        """A CPU reset: back to the bootloader at 0x41 with its RAM application gone."""
        self.counts["resets"] += 1
        self._power_off()
        self.pon = True
        self.cpu_ready_at = self.clock.now()
        self._sync_enable()
        self.regs[P.APPID] = P.APPID_BOOTLOADER

    def int_asserted(self) -> bool:
        """The INT line: asserted while an enabled interrupt bit is set."""
        if not self.enabled:
            return False
        self._advance()
        return bool(self.int_status & self.int_enab)

    # ---- bus side -----------------------------------------------------------------------
    def responds(self) -> bool:
        if not self.enabled:
            return False
        self._advance()
        return self.booting_until is None

    def i2c_write(self, data: bytes) -> None:
        self._advance()
        if not data:
            return
        reg = data[0]
        self.ptr = reg
        payload = data[1:]
        if not payload:
            return
        if reg == P.BL_CMD_STAT and not self.app:
            self._bl_frame(payload)
            return
        for i, v in enumerate(payload):
            self._write_reg((reg + i) & 0xFF, v)
        self.ptr = (reg + len(payload)) & 0xFF

    def i2c_read(self, n: int) -> bytes:
        self._advance()
        start = self.ptr
        out = bytearray(self.regs[start : start + n])
        out += bytes(n - len(out))
        if start == P.CID_RID and n > 32 and self.offered is not None and self._fault("wrong_cid"):
            out[0] = P.CID_HISTOGRAM_ELECTRICAL if out[0] != P.CID_HISTOGRAM_ELECTRICAL else P.CID_RESULT
        self.ptr = (start + n) & 0xFF
        return bytes(out)

    def _fault(self, kind: str) -> bool:
        if kind in self.armed:
            self.armed.remove(kind)
            return True
        p = getattr(self.faults, kind)
        return bool(p) and self._frng.random() < p

    # ---- registers ----------------------------------------------------------------------
    def _sync_enable(self) -> None:
        ready = self.cpu_ready_at is not None and self.clock.now() >= self.cpu_ready_at
        self.regs[P.ENABLE] = (P.ENABLE_CPU_READY if ready else 0) | (P.ENABLE_PON if self.pon else 0)

    def _write_reg(self, reg: int, v: int) -> None:
        if reg == P.ENABLE:
            if v & P.ENABLE_CPU_RESET:
                self._reset_to_bootloader()
                return
            if v & P.ENABLE_PON and not self.pon:
                self.pon = True
                self.cpu_ready_at = self.clock.now() + self.timing.cpu_ready_s
                self.regs[P.APPID] = P.APPID_BOOTLOADER
            elif not v & P.ENABLE_PON:
                self.pon = False
                self.cpu_ready_at = None
            self._sync_enable()
            return
        if not self._cpu_ready():
            return
        if not self.app:
            return  # the bootloader only listens at 0x08 (handled above) and ENABLE
        if reg == P.CMD_STAT:
            self._command(v)
        elif reg == P.INT_STATUS:
            self._clear_int(v)
        elif reg == P.INT_ENAB:
            self.int_enab = v
            self.regs[P.INT_ENAB] = v
        elif P.CONTENT <= reg < 0xE0 and self.regs[P.CID_RID] == P.CID_CONFIG and self.offered is None:
            self.regs[reg] = v

    def _cpu_ready(self) -> bool:
        return self.cpu_ready_at is not None and self.clock.now() >= self.cpu_ready_at

    # ---- bootloader ---------------------------------------------------------------------
    def _bl_status(self, code: int) -> None:
        self.regs[P.BL_CMD_STAT : P.BL_CMD_STAT + 3] = bytes([code, 0, P.bl_checksum(bytes([code, 0]))])

    def _bl_frame(self, frame: bytes) -> None:
        if not self._cpu_ready():
            return
        now = self.clock.now()
        if now < self.bl_busy_until:
            return  # busy: the frame is ignored (the host should have polled the status)
        self.bl_busy_until = now + self.timing.bl_command_s
        if len(frame) < 3 or frame[1] != len(frame) - 3:
            self._bl_status(P.BL_SIZE_ERROR)
            return
        if P.bl_checksum(frame[:-1]) != frame[-1]:
            self._bl_status(P.BL_CSUM_ERROR)
            return
        cmd, payload = frame[0], frame[2:-1]
        if cmd == P.BL_DOWNLOAD_INIT and len(payload) == 1:
            self.bl_inited = True
            self.ram_written = 0
        elif cmd == P.BL_ADDR_RAM and len(payload) == 2:
            self.ram_ptr = payload[0] | (payload[1] << 8)
        elif cmd == P.BL_W_RAM and self.bl_inited:
            end = self.ram_ptr + len(payload)
            if end > len(self.ram):
                self._bl_status(P.BL_SIZE_ERROR)
                return
            self.ram[self.ram_ptr : end] = payload
            self.ram_ptr = end
            self.ram_written += len(payload)
        elif cmd == P.BL_RAMREMAP_RESET and not payload:
            # No reply: the device reboots into the RAM image if it is the one it can run.
            ok = self.bl_inited and bytes(self.ram[: len(self.image)]) == self.image
            self.booting_until = now + self.timing.app_boot_s
            self._boot_ok = ok
            return
        else:
            self._bl_status(P.BL_SIZE_ERROR)
            return
        self._bl_status(0x00)
        # the status reads busy until the command has been executed
        self.regs[P.BL_CMD_STAT] = P.BL_BUSY_MIN
        self.regs[P.BL_CMD_STAT + 2] = P.bl_checksum(bytes([P.BL_BUSY_MIN, 0]))
        self._bl_pending_ok = True

    # ---- application --------------------------------------------------------------------
    def _layout(self) -> P.Layout | None:
        if self.mode == P.MODE_8X8:
            return P.Layout("8x8")
        name = P.SPAD_MAPS.get(self.config[P.CFG_SPAD_MAP])
        return None if name in (None, "8x8") else P.Layout(name)

    def _command(self, code: int) -> None:
        now = self.clock.now()
        t = self.timing
        if self.cmd is not None and self.cmd.done_at > now:
            return  # a command is running: ignored (its status still reads pending)
        reply, dt = P.STAT_OK, t.page_s
        if code == P.CMD_MEASURE:
            dt, reply = t.measure_s, P.STAT_ACCEPTED
            if self._layout() is None or self.measuring:
                reply = P.STAT_ERROR_UNKNOWN
        elif code == P.CMD_STOP:
            dt = t.stop_s
            self._stop()
        elif code in (P.CMD_LOAD_CONFIG_PAGE, P.CMD_WRITE_CONFIG_PAGE, P.CMD_CLEAR_STATUS,
                      P.CMD_LOAD_FACTORY_CALIB):
            if self.measuring and code != P.CMD_CLEAR_STATUS:
                reply = P.STAT_ERROR_UNKNOWN
        elif code in (P.CMD_MODE_8X8, P.CMD_MODE_LEGACY):
            dt = t.mode_switch_s
            if self.measuring:
                reply = P.STAT_ERROR_UNKNOWN
        elif code == P.CMD_I2C_ADDRESS:
            dt = t.address_s
        elif code == P.CMD_FACTORY_CALIB:
            dt = t.factory_calibration_s
        else:
            reply = P.STAT_ERROR_UNKNOWN
        self.cmd = _Cmd(code, now + dt, reply)
        self.regs[P.CMD_STAT] = code if code >= P.STAT_PENDING_MIN else P.STAT_PENDING_MIN

    def _finish_command(self) -> None:
        c = self.cmd
        self.regs[P.CMD_STAT] = c.reply
        self.cmd = None
        self._set_int(P.INT_COMMAND)
        if c.reply not in (P.STAT_OK, P.STAT_ACCEPTED):
            return
        if c.code == P.CMD_MEASURE:
            self.measuring = True
            self.sub = 0
            self.next_handover = c.done_at + self._period()
            self.drained_at = c.done_at
        elif c.code == P.CMD_LOAD_CONFIG_PAGE:
            self.tid = (self.tid + 1) & 0xFF
            self.regs[P.CID_RID] = P.CID_CONFIG
            self.regs[P.TID] = self.tid
            self.regs[P.SIZE : P.SIZE + 2] = P.CONFIG_SIZE.to_bytes(2, "little")
            self.regs[P.CONTENT : 0xE0] = self.config[P.CONTENT : 0xE0]
        elif c.code == P.CMD_WRITE_CONFIG_PAGE:
            if self.regs[P.CID_RID] == P.CID_CONFIG:
                self.config[P.CONTENT : 0xE0] = self.regs[P.CONTENT : 0xE0]
            else:
                self.regs[P.CMD_STAT] = P.STAT_ERROR_UNKNOWN
        elif c.code in (P.CMD_MODE_8X8, P.CMD_MODE_LEGACY):
            self.mode = P.MODE_8X8 if c.code == P.CMD_MODE_8X8 else P.MODE_LEGACY
            self.regs[P.MODE] = self.mode
            self._default_config()
        elif c.code == P.CMD_I2C_ADDRESS:
            self.address = self.config[P.CFG_I2C_ADDRESS] >> 1
        elif c.code == P.CMD_FACTORY_CALIB:
            self.regs[P.CALIB_STATUS] = P.CALIB_OK

    def _period(self) -> float:
        return max(1, int.from_bytes(self.config[P.CFG_PERIOD_MS : P.CFG_PERIOD_MS + 2], "little")) * 1e-3

    def _stop(self) -> None:
        self.measuring = False
        self.queue.clear()
        self.offered = None
        self.int_status &= ~(P.INT_HISTOGRAM | P.INT_RESULT)
        self.regs[P.INT_STATUS] = self.int_status

    def _set_int(self, bits: int) -> None:
        self.int_status |= bits
        self.regs[P.INT_STATUS] = self.int_status

    def _clear_int(self, bits: int) -> None:
        self.int_status &= ~bits
        self.regs[P.INT_STATUS] = self.int_status
        rec = self.offered
        if rec is None or not bits & rec.kind:
            return
        self.offered = None
        if self._fault("reset"):
            self._reset_to_bootloader()
            return
        if rec.kind == P.INT_HISTOGRAM:
            if self._fault("repeat"):
                self.queue.insert(0, rec)
                self._offer(same_tid=True)
                return
            if self.queue and self.queue[0].kind == P.INT_HISTOGRAM and self._fault("skip"):
                self.queue.pop(0)
                self.tid = (self.tid + 1) & 0xFF
        if self.queue:
            self._offer()
        else:
            self.drained_at = self.clock.now()

    def _offer(self, same_tid: bool = False) -> None:
        rec = self.queue.pop(0)
        if not same_tid:
            self.tid = (self.tid + 1) & 0xFF
        rec.data[1] = self.tid
        self.regs[P.CID_RID : P.CID_RID + len(rec.data)] = rec.data
        self.offered = rec
        self.counts["records"] += 1
        self._set_int(rec.kind)

    # ---- time ---------------------------------------------------------------------------
    def _advance(self) -> None:
        now = self.clock.now()
        if self.booting_until is not None and now >= self.booting_until:
            self.booting_until = None
            if self._boot_ok:
                self.app = True
                self.address = P.ADDRESS
                self._reset_app_state()
                self.regs[P.APPID] = P.APPID_APP
                self.regs[P.APP_VERSION : P.APP_VERSION + 3] = bytes([0x54, 0x41, 0x46])  # "TAF": emulated
                self.regs[P.MODE] = self.mode
                self.regs[P.CALIB_STATUS] = P.CALIB_NO_FACTORY
            else:
                self.regs[P.APPID] = P.APPID_BOOTLOADER
                self._bl_status(0x00)
        if self.cpu_ready_at is not None:
            self._sync_enable()
        if not self.app and self._bl_pending_ok and now >= self.bl_busy_until:
            self._bl_pending_ok = False
            self._bl_status(0x00)
        if self.app and self.cmd is not None and now >= self.cmd.done_at:
            self._finish_command()
        if self.app and self.measuring and self.offered is None and not self.queue:
            due = max(self.next_handover, self.drained_at)
            if now >= due:
                self._handover(due)

    def _handover(self, t: float) -> None:
        """A sub-capture completes at ``t``: its packets and result record become readable."""
        lay = self._layout()
        hist_on = bool(self.config[P.CFG_HIST_DUMP] & P.HIST_DUMP_RAW)
        if self.sub == 0 or self.frame_counts is None:
            self.frame_counts = self._draw_frame(lay)
            self.counts["frames"] += 1
        zones, ref = self.frame_counts
        s = self.sub
        if hist_on:
            for k in range(lay.n_configs):
                chans = np.zeros((P.N_CHANNELS, P.N_BINS), np.int64)
                chans[0] = ref
                for c in lay.channels:
                    chans[c] = zones[lay.zone_index(s, k, c)]
                for n in range(P.PACKETS_PER_CONFIG):
                    ch, plane = n % P.N_CHANNELS, n // P.N_CHANNELS
                    payload = ((chans[ch] >> (8 * plane)) & 0xFF).astype(np.uint8).tobytes()
                    head = bytes([P.CID_HISTOGRAM, 0, P.HIST_SIZE_FIELD & 0xFF, P.HIST_SIZE_FIELD >> 8,
                                  n, P.HIST_PAYLOAD, k])
                    self.queue.append(_Record(P.INT_HISTOGRAM, bytearray(head + payload)))
        self.queue.append(_Record(P.INT_RESULT, bytearray(self._result(lay, s, zones, ref, t))))
        self.result_number = (self.result_number + 1) & 0xFF
        self.sub = (s + 1) % lay.n_subcaptures
        self.next_handover = t + self._period()
        self._offer()

    def _draw_frame(self, lay: P.Layout) -> tuple[np.ndarray, np.ndarray]:
        """Counts of every TMF zone of the layout (index -> 128 bins) and of the reference."""
        zmap = self.zone_map.get(lay.name) or default_zone_map(lay, len(self.expected))
        lam = np.zeros((64 if lay.is_8x8 else 18, P.N_BINS))
        lam[np.asarray(zmap)] = self.expected
        lam_ref = self.reference
        if self.noise:
            counts, ref = self._rng.poisson(lam), self._rng.poisson(lam_ref)
        else:
            counts, ref = np.rint(lam), np.rint(lam_ref)
        counts = np.clip(counts, 0, P.MAX_COUNT).astype(np.int64)
        ref = np.clip(ref, 0, P.MAX_COUNT).astype(np.int64)
        self.last_frame = (counts[np.asarray(zmap)].copy(), ref.copy())
        return counts, ref

    def _result(self, lay: P.Layout, s: int, zones: np.ndarray, ref: np.ndarray, t: float) -> bytes:
        ref_peak = int(np.argmax(ref))
        targets = np.zeros((P.RESULT_ENTRIES, 2), np.int64)
        n_valid = 0
        for i in range(18):
            k, c = (i % 18) // 9, i % 9 + 1
            if k >= lay.n_configs or c not in lay.channels:
                continue
            h = zones[lay.zone_index(s, k, c)]
            if h.any():
                peak = int(np.argmax(h[ref_peak + 3 :])) + ref_peak + 3 if ref_peak + 3 < P.N_BINS else ref_peak
                mm = (peak - ref_peak) * self.bin_width_s * SPEED_OF_LIGHT / 2 * 1e3
                targets[i] = (255, int(min(max(mm, 0), 65535)))
                n_valid += 1
        number = (self.result_number & ~0x03) | s if lay.is_8x8 else self.result_number
        systick = (int(t / 0.2e-6) | 1) & 0xFFFFFFFF
        return P.pack_result(0, number, 25, n_valid, int(ref.min()) * P.N_BINS & 0xFFFFFFFF,
                             int(zones.sum()) & 0xFFFFFFFF, int(ref.sum()) & 0xFFFFFFFF, systick, targets)
