"""``tofjax acquire`` and ``tofjax baseline``: record captures from a TMF8828 rig (or an emulated one)."""

from __future__ import annotations

import sys

from ..errors import UserError

__all__ = ["register"]


def _faults(text: str | None):
    from .bus import BusFaults
    from .emulator import DeviceFaults

    if not text:
        return BusFaults(), DeviceFaults()
    bus, dev = {}, {}
    for item in text.split(","):
        key, _, val = item.partition("=")
        key = key.strip()
        try:
            p = float(val)
        except ValueError:
            raise UserError(f"--faults: {item!r} is not KIND=PROBABILITY") from None
        if not 0 <= p <= 1:
            raise UserError(f"--faults: {key} must be a probability in [0, 1], got {p}")
        if key in ("nack", "timeout", "corrupt"):
            bus[key] = p
        elif key in ("repeat", "skip", "wrong_cid", "reset"):
            dev[key] = p
        else:
            raise UserError(f"--faults: unknown fault {key!r}; known: nack, timeout, corrupt, repeat, skip, wrong_cid, reset")
    return BusFaults(**bus), DeviceFaults(**dev)


def _cmd_acquire(a, baseline: bool = False) -> int:
    from .recorder import AcquireOptions, acquire

    bus_faults, device_faults = _faults(a.faults)
    if (a.faults) and not a.emulate:
        raise UserError("--faults needs --emulate (faults are injected into the emulator)")
    opts = AcquireOptions(
        frames=a.frames, duration_s=getattr(a, "duration", None), emulate=a.emulate, image=a.image, bus=a.bus,
        bus_speed_hz=a.bus_speed, baseline=baseline, seed=a.seed, noise=False if a.no_noise else None,
        bus_faults=bus_faults, device_faults=device_faults, period_ms=a.period_ms, progress=not a.quiet,
        overwrite=a.overwrite,
    )
    if a.emulate and not a.image:
        print("tofjax: emulated rig with the synthetic test image (not firmware; a real rig needs --image)",
              file=sys.stderr)
    res = acquire(a.rig, a.out, opts)
    print(res.summary())
    return 130 if res.interrupted else 0


def _common(s) -> None:
    s.add_argument("rig", help="rig file (configs/rigs/*.toml), or a scene file / built-in scene name")
    s.add_argument("--out", required=True, help="output capture (.h5)")
    s.add_argument("--bus", type=int, default=None, help="I2C bus number N of /dev/i2c-N (default: the rig's, 1)")
    s.add_argument("--image", help="TMF8828 application image (Intel HEX or binary); not shipped with tofjax")
    s.add_argument("--emulate", action="store_true", help="emulated sensors from the scene's forward model")
    s.add_argument("--bus-speed", type=int, default=None, help="simulated bus speed in Hz with --emulate "
                   "(100000, 400000, 1000000; default the rig's)")
    s.add_argument("--period-ms", type=int, default=None, help="measurement period in ms (default the rig's, 33)")
    s.add_argument("--seed", type=int, default=0, help="emulator noise seed")
    s.add_argument("--no-noise", action="store_true", help="emulator without photon noise")
    s.add_argument("--faults", help="emulator fault rates, e.g. nack=0.01,reset=0.001 "
                   "(nack, timeout, corrupt per transfer; repeat, skip, wrong_cid, reset per record)")
    s.add_argument("--quiet", action="store_true", help="no live status line")


def _cmd_replay(a) -> int:
    from .recorder import replay

    res = replay(a.capture, a.out, speed=a.speed, progress=not a.quiet, overwrite=a.overwrite)
    wall_rate = res.frames / res.wall_s if res.wall_s > 0 else float("nan")
    what = f"wrote {res.path}" if a.out else f"replayed {res.path}"
    print(f"{'interrupted: ' if res.interrupted else ''}{what}: {res.frames} frames "
          f"({res.elapsed_s:.2f} s recorded, {res.wall_s:.2f} s now, {wall_rate:.1f} frames/s)")
    return 130 if res.interrupted else 0


def register(sub) -> None:
    s = sub.add_parser("acquire", help="record a capture from TMF8828 sensors over I2C (or --emulate)")
    _common(s)
    g = s.add_mutually_exclusive_group(required=True)
    g.add_argument("--frames", type=int, help="whole frames to record")
    g.add_argument("--duration", type=float, help="seconds to record (simulated seconds with --emulate)")
    s.set_defaults(func=_cmd_acquire)

    s = sub.add_parser("baseline", help="record a no-touch baseline capture (like acquire, nothing touching)")
    _common(s)
    s.add_argument("--frames", type=int, required=True, help="whole frames to record")
    s.set_defaults(func=lambda a: _cmd_acquire(a, baseline=True))

    s = sub.add_parser("replay", help="feed a recorded capture through the live acquisition pipeline")
    s.add_argument("capture", help="capture file (.h5)")
    s.add_argument("--speed", default="max", help="max (default), recorded, or a multiple of the recorded speed")
    s.add_argument("--out", help="write the frames again, as a live recording would (a copy through the pipeline)")
    s.add_argument("--quiet", action="store_true", help="no live status line")
    s.set_defaults(func=_cmd_replay)
