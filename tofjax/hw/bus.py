"""A simulated I2C bus: smbus2.SMBus's methods over emulated targets, a bit-level clock, faults.

The bus clock counts what goes over the wire (start, address and data bytes with their
ACK bits, repeated starts, stop) at the bus frequency, so a test can measure what a
frame costs at 100 kHz, 400 kHz or 1 MHz without waiting for it. Devices and the driver
share the :class:`SimClock`: the driver's sleeps advance it, so an emulated rig runs as
fast as the CPU allows while its timestamps are those of a real bus.
"""

from __future__ import annotations

import ctypes
import errno
import time
from dataclasses import dataclass, field
from typing import Protocol

import numpy as np
from smbus2 import i2c_msg
from smbus2.smbus2 import I2C_M_RD

__all__ = ["BusFaults", "I2CTarget", "RealClock", "SimBus", "SimClock", "SimIntPin", "SimPin", "TCA9548A"]


class SimClock:
    """Simulated time in seconds; ``sleep`` advances it instantly."""

    def __init__(self, t0: float = 0.0):
        self.t = float(t0)

    def now(self) -> float:
        return self.t

    def sleep(self, dt: float) -> None:
        if dt > 0:
            self.t += dt


class RealClock:
    """Wall time, for a real bus."""

    @staticmethod
    def now() -> float:
        return time.monotonic()

    @staticmethod
    def sleep(dt: float) -> None:
        if dt > 0:
            time.sleep(dt)


class I2CTarget(Protocol):
    """What the bus needs of a device: its address, whether it answers, and byte-level transfers."""

    address: int

    def responds(self) -> bool: ...

    def i2c_write(self, data: bytes) -> None: ...

    def i2c_read(self, n: int) -> bytes: ...


@dataclass(frozen=True)
class BusFaults:
    """Bus-level faults, as probabilities per transfer (deterministic for a given seed).

    - ``nack``: the address is not acknowledged: ``OSError(EREMOTEIO)``, nothing reaches the device.
    - ``timeout``: the transfer times out (``OSError(ETIMEDOUT)``) after ``timeout_s`` of bus time.
    - ``corrupt``: a bit error in the header of a record read (> 32 bytes). Bins carry no
      checksum in the TMF8828 protocol, so an error there cannot be seen by any driver;
      the emulator therefore corrupts only what a driver can check (documented).
    """

    nack: float = 0.0
    timeout: float = 0.0
    corrupt: float = 0.0
    timeout_s: float = 0.025
    seed: int = 0

    def __post_init__(self):
        for k in ("nack", "timeout", "corrupt"):
            if not 0.0 <= getattr(self, k) <= 1.0:
                raise ValueError(f"BusFaults.{k} must be a probability, got {getattr(self, k)!r}")


@dataclass
class BusStats:
    transfers: int = 0
    bytes: int = 0
    bits: int = 0
    busy_s: float = 0.0
    faults: dict[str, int] = field(default_factory=lambda: {"nack": 0, "timeout": 0, "corrupt": 0})


class SimPin:
    """An output pin (gpiozero's ``DigitalOutputDevice`` API: ``on``, ``off``, ``value``) wired to an emulated device's enable."""

    def __init__(self, target, clock: SimClock | None = None):
        self.target = target
        self.value = 0

    def on(self) -> None:
        self.value = 1
        self.target.set_enable(True)

    def off(self) -> None:
        self.value = 0
        self.target.set_enable(False)

    def close(self) -> None:
        pass


class SimIntPin:
    """An input pin (gpiozero's ``DigitalInputDevice`` API: ``value``) wired to an emulated device's INT line."""

    def __init__(self, target):
        self.target = target

    @property
    def value(self) -> int:
        return int(self.target.int_asserted())

    def close(self) -> None:
        pass


class TCA9548A:
    """An emulated TCA9548A-style I2C multiplexer: one control byte, the mask of connected channels."""

    def __init__(self, address: int = 0x70):
        self.address = address
        self.mask = 0

    def responds(self) -> bool:
        return True

    def i2c_write(self, data: bytes) -> None:
        if data:
            self.mask = data[-1]

    def i2c_read(self, n: int) -> bytes:
        return bytes([self.mask]) * n


class SimBus:
    """smbus2.SMBus's methods over emulated targets, with a simulated clock and faults.

    Targets behind a multiplexer are attached with ``channel``; they are reachable only while
    the mux's mask selects their channel. Several targets answering one address (two sensors
    enabled at 0x41) do what open-drain lines do: their read bytes are ANDed.
    """

    def __init__(self, frequency_hz: float = 400_000, *, clock: SimClock | None = None, faults: BusFaults = BusFaults(),
                 overhead_s: float = 0.0):
        if frequency_hz <= 0:
            raise ValueError(f"frequency_hz must be > 0, got {frequency_hz}")
        self.frequency_hz = float(frequency_hz)
        self.clock = clock or SimClock()
        self.faults = faults
        self.overhead_s = overhead_s
        self.stats = BusStats()
        self._rng = np.random.default_rng(faults.seed)
        self._targets: list[tuple[I2CTarget, int | None]] = []
        self._mux: TCA9548A | None = None
        #: one-shot bus faults to fire on the next transfers, in order (tests arm them)
        self.armed: list[str] = []

    # ---- wiring -------------------------------------------------------------------------
    def attach(self, target: I2CTarget, channel: int | None = None) -> I2CTarget:
        if isinstance(target, TCA9548A):
            self._mux = target
        self._targets.append((target, channel))
        return target

    def _visible(self, addr: int) -> list[I2CTarget]:
        mask = self._mux.mask if self._mux is not None else 0
        return [
            t for t, ch in self._targets
            # responds() first: it lets the device catch up with the clock (an address change)
            if (ch is None or (mask >> ch) & 1) and t.responds() and t.address == addr
        ]

    # ---- clock and faults ---------------------------------------------------------------
    def _spend(self, bits: int, nbytes: int) -> None:
        dt = bits / self.frequency_hz + self.overhead_s
        self.stats.transfers += 1
        self.stats.bits += bits
        self.stats.bytes += nbytes
        self.stats.busy_s += dt
        self.clock.sleep(dt)

    def _fault(self) -> str | None:
        if self.armed:
            return self.armed.pop(0)
        f = self.faults
        if f.nack or f.timeout or f.corrupt:
            u = self._rng.random()
            if u < f.nack:
                return "nack"
            if u < f.nack + f.timeout:
                return "timeout"
            if u < f.nack + f.timeout + f.corrupt:
                return "corrupt"
        return None

    def _transaction(self, parts: list[tuple[int, bool, bytes | int]]) -> list[bytes]:
        """One transaction: a list of (addr, is_read, data or length) joined by repeated starts."""
        fault = self._fault()
        nbytes = sum(p[2] if p[1] else len(p[2]) for p in parts)
        bits = 1 + sum(9 + 9 * (p[2] if p[1] else len(p[2])) + 1 for p in parts)  # start, per part addr+data+(r)start/stop
        if fault == "nack":
            self.stats.faults["nack"] += 1
            self._spend(1 + 9 + 1, 0)
            raise OSError(errno.EREMOTEIO, "Remote I/O error (emulated NACK)")
        if fault == "timeout":
            self.stats.faults["timeout"] += 1
            self._spend(bits, nbytes)
            self.clock.sleep(self.faults.timeout_s)
            raise OSError(errno.ETIMEDOUT, "Connection timed out (emulated)")
        out = []
        for addr, is_read, data in parts:
            targets = self._visible(addr)
            if not targets:
                self._spend(1 + 9 + 1, 0)
                raise OSError(errno.EREMOTEIO, f"Remote I/O error: no device answers at {addr:#04x}")
            if is_read:
                reads = [t.i2c_read(data) for t in targets]
                buf = reads[0] if len(reads) == 1 else bytes(np.bitwise_and.reduce([np.frombuffer(r, np.uint8) for r in reads]))
                if fault == "corrupt" and data > 32:
                    self.stats.faults["corrupt"] += 1
                    b = bytearray(buf)
                    i = int(self._rng.integers(0, 7))
                    b[i] ^= 1 << int(self._rng.integers(0, 8))
                    buf = bytes(b)
                out.append(buf)
            else:
                for t in targets:
                    t.i2c_write(bytes(data))
        self._spend(bits, nbytes)
        return out

    # ---- smbus2.SMBus's methods ---------------------------------------------------------
    def i2c_rdwr(self, *msgs: i2c_msg) -> None:
        parts = []
        for m in msgs:
            if m.flags & I2C_M_RD:
                parts.append((m.addr, True, int(m.len)))
            else:
                parts.append((m.addr, False, bytes(m)))
        reads = iter(self._transaction(parts))
        for m in msgs:
            if m.flags & I2C_M_RD:
                data = next(reads)
                ctypes.memmove(m.buf, data, len(data))

    def read_byte_data(self, i2c_addr: int, register: int, force=None) -> int:
        return self._transaction([(i2c_addr, False, bytes([register])), (i2c_addr, True, 1)])[0][0]

    def write_byte_data(self, i2c_addr: int, register: int, value: int, force=None) -> None:
        self._transaction([(i2c_addr, False, bytes([register, value & 0xFF]))])

    def read_i2c_block_data(self, i2c_addr: int, register: int, length: int, force=None) -> list[int]:
        if length > 32:
            raise ValueError("Desired block length over 32 bytes")  # smbus2's own limit and message
        return list(self._transaction([(i2c_addr, False, bytes([register])), (i2c_addr, True, length)])[0])

    def write_i2c_block_data(self, i2c_addr: int, register: int, data, force=None) -> None:
        if len(data) > 32:
            raise ValueError("Data length cannot exceed 32 bytes")
        self._transaction([(i2c_addr, False, bytes([register, *data]))])

    def write_byte(self, i2c_addr: int, value: int, force=None) -> None:
        self._transaction([(i2c_addr, False, bytes([value & 0xFF]))])

    def read_byte(self, i2c_addr: int, force=None) -> int:
        return self._transaction([(i2c_addr, True, 1)])[0][0]

    def close(self) -> None:
        pass

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()
