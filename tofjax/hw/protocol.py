"""TMF8828 I2C protocol: registers, commands, bootloader frames, record layouts, zone layouts.

Every constant here comes from ``../shared/tmf8828-protocol.md`` (facts gathered from
public drivers, not from the datasheet). Where this module needs something that page does
not give, it says so next to the constant (``NOT ON THE PROTOCOL PAGE``) and
``docs/acquisition.md`` lists those assumptions. The driver and the emulator share this
module, so they cannot disagree with each other; real hardware may still disagree with both.
"""

from __future__ import annotations

import struct
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..errors import UserError

# ---- bus and power-up ------------------------------------------------------------------------
ADDRESS = 0x41
ENABLE = 0xE0
ENABLE_CPU_RESET = 0x80
ENABLE_CPU_READY = 0x40
ENABLE_PON = 0x01
ENABLE_STANDBY = 0x02
#: bits 5:4 of ENABLE: where the CPU boots from.
POWERUP_SELECT_SHIFT = 4
POWERUP_FUSES, POWERUP_BOOTLOADER, POWERUP_RAM = 0, 1, 2

APPID = 0x00
APPID_BOOTLOADER = 0x80
APPID_APP = 0x03
APP_VERSION = 0x01  # 0x01..0x03

# ---- bootloader ------------------------------------------------------------------------------
BL_CMD_STAT = 0x08
BL_DOWNLOAD_INIT = 0x14
BL_ADDR_RAM = 0x43
BL_W_RAM = 0x41
BL_RAMREMAP_RESET = 0x11
BL_DOWNLOAD_INIT_SEED = 0x29
BL_MAX_PAYLOAD = 128
BL_OK = bytes([0x00, 0x00, 0xFF])
BL_SIZE_ERROR = 0x01
BL_CSUM_ERROR = 0x02
BL_BUSY_MIN = 0x10
#: Where the application image lives; ADDR_RAM 0x0000 means this address.
RAM_BASE = 0x00200000

# ---- application registers -------------------------------------------------------------------
APP_STATUS = 0x04  # 0x04-0x06: application / measure / algorithm status
CALIB_STATUS = 0x07
CMD_STAT = 0x08
MODE = 0x10
MODE_LEGACY = 0x00
MODE_8X8 = 0x08
CID_RID = 0x20
TID = 0x21
SIZE = 0x22  # 0x22-0x23
CONTENT = 0x24  # 0x24-0xDF
INT_STATUS = 0xE1
INT_ENAB = 0xE2

CALIB_OK, CALIB_NO_FACTORY, CALIB_SPAD_MISMATCH = 0x00, 0x31, 0x32

# commands (write to CMD_STAT)
CMD_MEASURE = 0x10
CMD_CLEAR_STATUS = 0x11
CMD_WRITE_CONFIG_PAGE = 0x15
CMD_LOAD_CONFIG_PAGE = 0x16
CMD_LOAD_FACTORY_CALIB = 0x19
CMD_FACTORY_CALIB = 0x20
CMD_I2C_ADDRESS = 0x21
CMD_MODE_8X8 = 0x6C
CMD_MODE_LEGACY = 0x65
CMD_STOP = 0xFF
STAT_OK = 0x00
STAT_ACCEPTED = 0x01  # measure's accepted reply
STAT_PENDING_MIN = 0x10
#: NOT ON THE PROTOCOL PAGE: the error code the emulator answers an unknown command with
#: (the page only says 0x02-0x0F are errors).
STAT_ERROR_UNKNOWN = 0x02

# interrupt bits
INT_RESULT = 0x02
INT_HISTOGRAM = 0x08
INT_COMMAND = 0x20
INT_ERROR = 0x40

# ---- common config page (CID 0x16, size 188) --------------------------------------------------
CID_CONFIG = 0x16
CONFIG_SIZE = 188
CFG_PERIOD_MS = 0x24  # u16
CFG_KILO_ITERATIONS = 0x26  # u16
CFG_CONFIDENCE = 0x30
CFG_SPAD_MAP = 0x34
CFG_ALGO = 0x35
CFG_HIST_DUMP = 0x39
CFG_I2C_ADDRESS = 0x3B
HIST_DUMP_RAW = 0x01
HIST_DUMP_ELECTRICAL = 0x02
DEFAULT_PERIOD_MS = 33
SPAD_MAP_8X8 = 15

# ---- records ---------------------------------------------------------------------------------
CID_RESULT = 0x10
RESULT_LEN = 132  # bytes read from 0x20
CID_HISTOGRAM = 0x81
CID_HISTOGRAM_ELECTRICAL = 0x82
HIST_PACKET_LEN = 135  # 4 header + 3 sub-header + 128 bins
HIST_PAYLOAD = 128
#: Size field of a histogram packet: what follows the 4-byte header.
HIST_SIZE_FIELD = HIST_PACKET_LEN - 4
RESULT_SIZE_FIELD = RESULT_LEN - 4
N_CHANNELS = 10  # channel 0: the reference SPAD; 1-9: zones
N_PLANES = 3  # 24-bit bins, one byte plane per packet
PACKETS_PER_CONFIG = N_CHANNELS * N_PLANES  # 30
N_BINS = 128
MAX_COUNT = 2**24 - 1
RESULT_ENTRIES = 36


def bl_checksum(data: bytes | bytearray) -> int:
    """Bootloader checksum: bitwise NOT of the 8-bit sum of cmd, len and payload."""
    return (~sum(data)) & 0xFF


def bl_frame(cmd: int, payload: bytes | bytearray = b"") -> bytes:
    """A bootloader frame ``[cmd, len, payload..., csum]`` (written to register 0x08)."""
    if len(payload) > BL_MAX_PAYLOAD:
        raise ValueError(f"bootloader payload of {len(payload)} bytes > {BL_MAX_PAYLOAD}")
    body = bytes([cmd, len(payload)]) + bytes(payload)
    return body + bytes([bl_checksum(body)])


# ---- zone layouts ----------------------------------------------------------------------------
#: NOT ON THE PROTOCOL PAGE: SPAD map ids of the legacy layouts (from public driver sources;
#: check against the datasheet). The page gives only 15 for 8x8. In legacy mode the SPAD map
#: decides the layout, so driver and emulator both read it from this table.
SPAD_MAPS = {1: "3x3", 6: "3x6", 7: "4x4", 15: "8x8"}
DEFAULT_SPAD_MAP = {v: k for k, v in SPAD_MAPS.items()}


@dataclass(frozen=True)
class Layout:
    """How a TMF8828 mode lays out its zones over configurations, channels and sub-captures.

    A *TMF zone index* names one zone of the mode: in legacy layouts ``9 k + (c - 1)``
    (configuration ``k``, channel ``c``); in 8x8 ``8 row + col``.
    """

    name: str

    @property
    def is_8x8(self) -> bool:
        return self.name == "8x8"

    @property
    def mode_register(self) -> int:
        return MODE_8X8 if self.is_8x8 else MODE_LEGACY

    @property
    def n_configs(self) -> int:
        return 1 if self.name == "3x3" else 2

    @property
    def n_subcaptures(self) -> int:
        return 4 if self.is_8x8 else 1

    @property
    def channels(self) -> tuple[int, ...]:
        """Zone channels used per configuration (channel 9 is unused in 4x4 and 8x8)."""
        return tuple(range(1, 10)) if self.name in ("3x3", "3x6") else tuple(range(1, 9))

    @property
    def packets_per_subcapture(self) -> int:
        return PACKETS_PER_CONFIG * self.n_configs

    @property
    def n_zones(self) -> int:
        return 64 if self.is_8x8 else len(self.channels) * self.n_configs

    def slots(self) -> list[tuple[int, int, int]]:
        """Every (sub-capture, configuration, channel) that carries a zone, in TMF zone index order."""
        out: dict[int, tuple[int, int, int]] = {}
        for s in range(self.n_subcaptures):
            for k in range(self.n_configs):
                for c in self.channels:
                    out[self.zone_index(s, k, c)] = (s, k, c)
        return [out[i] for i in sorted(out)]

    def zone_index(self, s: int, k: int, c: int) -> int:
        """TMF zone index of sub-capture ``s``, configuration ``k``, channel ``c``."""
        if self.is_8x8:
            # The protocol page's placement (check orientation on hardware).
            row = 7 - 2 * ((c - 1) // 2) - s // 2
            col = 4 * ((c - 1) % 2) + 2 * (s % 2) + k
            return 8 * row + col
        return 9 * k + (c - 1)


LAYOUTS = ("3x3", "3x6", "4x4", "8x8")


def layout_for(zones: int, name: str = "auto") -> Layout:
    """The layout for a scene with ``zones`` zones: ``name``, or the smallest that holds them."""
    if name == "auto":
        for cand in ("3x3", "4x4", "3x6", "8x8"):
            if Layout(cand).n_zones >= zones:
                return Layout(cand)
        raise UserError(f"a scene with {zones} zones per sensor does not fit a TMF8828 (at most 64, in 8x8 mode)")
    if name not in LAYOUTS:
        raise UserError(f"layout {name!r}: must be one of auto, {', '.join(LAYOUTS)}")
    lay = Layout(name)
    if zones > lay.n_zones:
        raise UserError(f"layout {name} has {lay.n_zones} zones but the scene has {zones} per sensor")
    return lay


# ---- packet parsing --------------------------------------------------------------------------
@dataclass(frozen=True)
class PacketHeader:
    cid: int
    tid: int
    size: int
    number: int  # sub-packet 0-29
    length: int  # payload length (128)
    config: int  # configuration index 0/1


def parse_histogram_header(data: bytes | bytearray) -> PacketHeader:
    cid, tid, size = data[0], data[1], data[2] | (data[3] << 8)
    return PacketHeader(cid, tid, size, data[4], data[5], data[6])


@dataclass(frozen=True)
class Result:
    """The parts of a result record (CID 0x10) the recorder keeps."""

    tid: int
    number: int
    temperature_c: int
    n_valid: int
    ambient: int
    photon_count: int
    reference_count: int
    systick: int
    #: (36, 2): confidence, distance_mm
    targets: np.ndarray

    @property
    def subcapture(self) -> int:
        return self.number & 0x03


_RESULT_HEAD = struct.Struct("<BBHBbBxIIII")


def parse_result(data: bytes | bytearray) -> Result:
    cid, tid, size, number, temp, n_valid, ambient, photons, ref, systick = _RESULT_HEAD.unpack_from(data, 0)
    ent = np.frombuffer(bytes(data[0x38 - 0x20 : 0x38 - 0x20 + 3 * RESULT_ENTRIES]), np.uint8).reshape(-1, 3)
    targets = np.stack([ent[:, 0].astype(np.int32), ent[:, 1].astype(np.int32) | (ent[:, 2].astype(np.int32) << 8)], 1)
    return Result(tid, number, temp, n_valid, ambient, photons, ref, systick, targets)


def pack_result(tid: int, number: int, temperature_c: int, n_valid: int, ambient: int, photons: int, ref: int,
                systick: int, targets: np.ndarray) -> bytes:
    head = _RESULT_HEAD.pack(CID_RESULT, tid & 0xFF, RESULT_SIZE_FIELD, number & 0xFF, temperature_c, n_valid,
                             ambient, photons, ref, systick)
    t = np.asarray(targets, np.int64).reshape(RESULT_ENTRIES, 2)
    ent = np.stack([t[:, 0] & 0xFF, t[:, 1] & 0xFF, (t[:, 1] >> 8) & 0xFF], 1).astype(np.uint8).tobytes()
    out = head + ent
    return out + bytes(RESULT_LEN - len(out))


# ---- application images ----------------------------------------------------------------------
class ImageError(UserError):
    """An application image file is missing or not a usable Intel HEX / binary image."""


def parse_intel_hex(text: str, source: str = "image") -> tuple[int, bytes]:
    """Parse Intel HEX into (start address, bytes) of its one contiguous segment.

    Supports record types 00 (data), 01 (end), 02 (extended segment address), 03/05
    (start address, ignored) and 04 (extended linear address); checks every record's
    checksum. Gaps are refused: the bootloader writes one contiguous range.
    """
    base = 0
    chunks: dict[int, bytes] = {}
    ended = False
    for lineno, line in enumerate(text.splitlines(), 1):
        line = line.strip()
        if not line:
            continue
        if ended:
            raise ImageError(f"{source}:{lineno}: data after the end-of-file record")
        if not line.startswith(":"):
            raise ImageError(f"{source}:{lineno}: not an Intel HEX record (no ':')")
        try:
            raw = bytes.fromhex(line[1:])
        except ValueError:
            raise ImageError(f"{source}:{lineno}: not hexadecimal") from None
        if len(raw) < 5 or len(raw) != raw[0] + 5:
            raise ImageError(f"{source}:{lineno}: record length does not match its byte count")
        if sum(raw) & 0xFF:
            raise ImageError(f"{source}:{lineno}: record checksum mismatch")
        n, addr, rtype, data = raw[0], (raw[1] << 8) | raw[2], raw[3], raw[4 : 4 + raw[0]]
        if rtype == 0x00:
            chunks[base + addr] = data
        elif rtype == 0x01:
            ended = True
        elif rtype == 0x02:
            base = ((data[0] << 8) | data[1]) << 4
        elif rtype == 0x04:
            base = ((data[0] << 8) | data[1]) << 16
        elif rtype in (0x03, 0x05):
            pass
        else:
            raise ImageError(f"{source}:{lineno}: unknown record type {rtype:#04x}")
        del n
    if not ended:
        raise ImageError(f"{source}: no end-of-file record (truncated?)")
    if not chunks:
        raise ImageError(f"{source}: no data records")
    start = min(chunks)
    out = bytearray()
    for a in sorted(chunks):
        if a != start + len(out):
            raise ImageError(
                f"{source}: the image is not one contiguous segment (gap or overlap at {a:#010x}); "
                "the bootloader writes one range"
            )
        out += chunks[a]
    return start, bytes(out)


def to_intel_hex(data: bytes, start: int = RAM_BASE, width: int = 16) -> str:
    """Write bytes as Intel HEX (extended linear address records), for tests and tools."""

    def rec(addr: int, rtype: int, payload: bytes) -> str:
        body = bytes([len(payload), (addr >> 8) & 0xFF, addr & 0xFF, rtype]) + payload
        return ":" + (body + bytes([(-sum(body)) & 0xFF])).hex().upper()

    lines, upper = [], None
    for off in range(0, len(data), width):
        a = start + off
        if a >> 16 != upper:
            upper = a >> 16
            lines.append(rec(0, 0x04, bytes([(upper >> 8) & 0xFF, upper & 0xFF])))
        lines.append(rec(a & 0xFFFF, 0x00, data[off : off + width]))
    lines.append(rec(0, 0x01, b""))
    return "\n".join(lines) + "\n"


def load_image(path: str | Path) -> bytes:
    """Read a user-supplied application image: Intel HEX (``.hex``/``.ihex``, one segment at
    0x00200000) or raw binary (anything else, loaded at 0x00200000)."""
    path = Path(path)
    if not path.is_file():
        raise ImageError(
            f"{path}: no such image file (the TMF8828 application image is ams-OSRAM's and not shipped "
            "with tofjax: see docs/acquisition.md for where to get it)"
        )
    raw = path.read_bytes()
    if path.suffix.lower() in (".hex", ".ihex", ".ihx") or raw[:1] == b":":
        try:
            text = raw.decode("ascii")
        except UnicodeDecodeError:
            raise ImageError(f"{path}: starts like Intel HEX but is not ASCII") from None
        start, data = parse_intel_hex(text, str(path))
        if start != RAM_BASE:
            raise ImageError(f"{path}: image starts at {start:#010x}, the TMF8828 application lives at {RAM_BASE:#010x}")
    else:
        data = raw
    if not data:
        raise ImageError(f"{path}: empty image")
    if len(data) > 0x10000:
        raise ImageError(f"{path}: {len(data)} bytes is too large for the 16-bit RAM address of ADDR_RAM")
    return data


#: Marks the synthetic image: the emulator runs only images that start with it (a real
#: device runs only ams-OSRAM's image; the emulator runs only this one).
SYNTHETIC_MAGIC = b"TOFJAX-SYNTHETIC-TMF8828-IMAGE\x00\x00"


def synthetic_image(size: int = 7168, seed: int = 8828) -> bytes:
    """A synthetic stand-in for the application image (~7 KB like the real one).

    It is NOT firmware: it only exercises the download path (framing, checksums, address
    auto-increment) against the emulator, which checks that the RAM holds exactly these bytes.
    """
    body = np.random.default_rng(seed).integers(0, 256, size - len(SYNTHETIC_MAGIC), dtype=np.uint8).tobytes()
    return SYNTHETIC_MAGIC + body
