"""Simulated indentation captures reproducing seed 001's protocol (section III).

A robot presses a round indenter into the skin at one point ``distance_m`` in
front of one sensor, at a constant indentation velocity, until the force reaches
its target; holds the position for ``hold_s``; and retracts at the same velocity.
The force reference runs at ``force_rate_hz`` (100 Hz, the JR3 sensor), the ToF
sensor at ``frame_rate_hz`` (9 Hz). Each capture starts with ``baseline_s`` of
frames with nothing touching (the baseline the dual-input models use).

What the optics see, in order:

1. **Contact mechanics**: a Hertz-like force-depth law ``F = k d^1.5``; the robot
   moves at ``v``, so force rises as ``(v t)^1.5`` until the target.
2. **Viscoelastic lag**: the silicone's deformation follows the force through a
   first-order lag of time constant ``lag_s`` (the optical signal trails fast
   indentations, which is why fast indentations are harder).
3. **Saturating force-to-signal**: the touch strength of the forward model is
   ``strength_max (1 - exp(-F_lag / strength_force_n))`` and the contact radius
   grows as ``sqrt(R d)`` (deformed contact), capped at the indenter radius.
4. **Exposure**: a ToF frame integrates over the ``1 / frame_rate_hz`` before its
   timestamp; the force channel of the capture is the 100 Hz reference averaged
   over the same window (:func:`align_force`).
5. **Ambient light** (seed 001 Fig. 8): each capture has its own ambient level
   (log-uniform in ``ambient_counts_range``) that drifts slowly; it adds a vertical
   offset and flattens the response (the SPADs' gain drops as
   ``1 / (1 + a / ambient_flattening_counts)``).
6. **Photon noise**: Poisson counts of the forward model's expected histograms.

The forward model is evaluated for every frame at once (``jax.vmap`` in chunks),
so a whole protocol takes seconds.

**Positions** (beyond seed 001, issue 17): ``positions_m`` repeats the protocol at a
grid of contact positions ``[distance, lateral]`` from the sensor (training and test
captures at each); ``unseen_positions_m`` gets test captures only (split ``unseen``);
``two_contacts_m`` gets test captures with two simultaneous contacts, each pressed to
its own random forces (split ``two_contacts``; the capture's ``force`` channel is the
first contact's, ``truth.contact_forces_n`` holds both, frame by frame).
"""

from __future__ import annotations

import dataclasses
import functools
import json
from dataclasses import dataclass
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

from ..capture import Capture, write_capture
from ..config import ConfigError, from_dict, to_dict
from ..model import ModelOptions, Params, build_model
from ..scene import Scene, Touch, load_scene

__all__ = [
    "Protocol",
    "align_force",
    "contact_position",
    "generate",
    "indentation_force",
    "lag",
    "touch_strength",
]


#: The most force-reference samples a protocol may ask for (float64: 0.8 GB); beyond, generation runs out of memory.
MAX_FORCE_SAMPLES = 1e8


@dataclass(frozen=True)
class Protocol:
    """Seed 001's indentation protocol, and the physics of the simulated skin.

    Defaults reproduce section III: 150 mm in front of sensor 0 of SoftSkin,
    0.1 / 1 / 5 mm/s, 10-60 N x 5 repetitions for training, 10 unseen random
    forces per velocity for testing, 5 s hold, 9 Hz frames, 100 Hz force.
    """

    scene: str = "softskin"
    sensor: int = 0
    distance_m: float = 0.15
    #: Sideways offset of the contact from the sensor's optical axis.
    lateral_m: float = 0.0
    indenter_radius_m: float = 0.011
    velocities_mm_s: tuple[float, ...] = (0.1, 1.0, 5.0)
    train_forces_n: tuple[float, ...] = (10.0, 20.0, 30.0, 40.0, 50.0, 60.0)
    repetitions: int = 5
    test_forces_per_velocity: int = 10
    test_force_range_n: tuple[float, float] = (8.0, 60.0)
    #: Test captures per velocity (each with its own ambient light); forces are shared out.
    test_captures_per_velocity: int = 2
    hold_s: float = 5.0
    rest_s: float = 3.0
    baseline_s: float = 3.0
    frame_rate_hz: float = 9.0
    force_rate_hz: float = 100.0
    #: k of F = k d^1.5 (d in mm): 60 N at 4 mm.
    stiffness_n_per_mm1p5: float = 7.5
    lag_s: float = 0.5
    strength_max: float = 4.0
    strength_force_n: float = 40.0
    ambient_counts_range: tuple[float, float] = (10.0, 300.0)
    ambient_flattening_counts: float = 600.0
    #: Relative amplitude of the slow ambient drift within a capture.
    ambient_drift: float = 0.05
    ambient_drift_period_s: float = 120.0
    force_noise_n: float = 0.05
    #: Contact positions [distance_m, lateral_m] of the training (and seen-test) captures;
    #: empty: the one position (distance_m, lateral_m), seed 001.
    positions_m: tuple[tuple[float, float], ...] = ()
    #: Positions held out of training: test captures only (split "unseen").
    unseen_positions_m: tuple[tuple[float, float], ...] = ()
    #: Pairs of positions pressed at once, each to its own forces (split "two_contacts").
    two_contacts_m: tuple[tuple[tuple[float, float], tuple[float, float]], ...] = ()
    #: Forward-model precision for generation (float32 is ~2x faster; photon noise dwarfs its error).
    dtype: str = "float32"
    seed: int = 0

    def __post_init__(self):
        for k in (
            "distance_m", "indenter_radius_m", "hold_s", "frame_rate_hz", "force_rate_hz",
            "stiffness_n_per_mm1p5", "lag_s", "strength_max", "strength_force_n", "ambient_flattening_counts",
            "ambient_drift_period_s",
        ):
            if getattr(self, k) <= 0:
                raise ConfigError(f"{k}: must be > 0, got {getattr(self, k)!r}")
        for k in ("rest_s", "baseline_s", "force_noise_n", "ambient_drift"):
            if getattr(self, k) < 0:
                raise ConfigError(f"{k}: must be >= 0, got {getattr(self, k)!r}")
        if not self.velocities_mm_s or min(self.velocities_mm_s) <= 0:
            raise ConfigError(f"velocities_mm_s: must be a non-empty list of positive values, got {self.velocities_mm_s!r}")
        if not self.train_forces_n or min(self.train_forces_n) <= 0:
            raise ConfigError(f"train_forces_n: must be a non-empty list of positive forces, got {self.train_forces_n!r}")
        lo, hi = self.test_force_range_n
        if not 0 < lo < hi:
            raise ConfigError(f"test_force_range_n: must be [low, high] with 0 < low < high, got {self.test_force_range_n!r}")
        lo, hi = self.ambient_counts_range
        if not 0 <= lo <= hi:
            raise ConfigError(f"ambient_counts_range: must be [low, high] with 0 <= low <= high, got {self.ambient_counts_range!r}")
        if self.repetitions < 1 or self.test_captures_per_velocity < 1 or self.test_forces_per_velocity < 0:
            raise ConfigError("repetitions and test_captures_per_velocity must be >= 1, test_forces_per_velocity >= 0")
        if self.force_rate_hz < self.frame_rate_hz:
            raise ConfigError("force_rate_hz: the force reference must be sampled at least as fast as the frames")
        if self.dtype not in ("float32", "float64"):
            raise ConfigError(f"dtype: must be float32 or float64, got {self.dtype!r}")
        if self.baseline_s * self.frame_rate_hz < 1:
            raise ConfigError("baseline_s: must hold at least one frame (the dual-input models need a baseline)")
        samples = self.estimated_force_samples()
        if not samples <= MAX_FORCE_SAMPLES:
            raise ConfigError(
                f"the protocol's force reference would hold about {samples:.3g} samples (more than {MAX_FORCE_SAMPLES:.0e}: "
                "memory); shorten hold_s / rest_s / baseline_s, lower force_rate_hz or use fewer presses"
            )

    def estimated_force_samples(self) -> float:
        """About how many force-reference samples the protocol's captures hold, all together (an upper
        estimate: every press to the largest force, its ramps at each velocity)."""
        f_max = max(max(self.train_forces_n), self.test_force_range_n[1])
        depth_mm = (f_max / self.stiffness_n_per_mm1p5) ** (2.0 / 3.0)
        presses = self.repetitions * len(self.train_forces_n) * max(len(self.train_positions), 1) + self.test_forces_per_velocity
        seconds = sum(presses * (self.hold_s + self.rest_s + 2.0 * depth_mm / v) + self.baseline_s
                      for v in self.velocities_mm_s)
        return seconds * self.force_rate_hz * (1 + len(self.unseen_positions_m) + len(self.two_contacts_m))

    @property
    def train_positions(self) -> tuple[tuple[float, float], ...]:
        return self.positions_m or ((self.distance_m, self.lateral_m),)

    @property
    def baseline_frames(self) -> int:
        return int(round(self.baseline_s * self.frame_rate_hz))

    def load_scene(self) -> Scene:
        scene = load_scene(self.scene).require_waveguide("the force protocol", self.scene).without_touches()
        if not 0 <= self.sensor < scene.n_sensors:
            raise ConfigError(f"sensor: {self.sensor} is not a sensor of scene '{scene.name}' ({scene.n_sensors} sensors)")
        named = [("positions_m", q) for q in self.positions_m] + [("unseen_positions_m", q) for q in self.unseen_positions_m]
        named += [("two_contacts_m", q) for pair in self.two_contacts_m for q in pair]
        for key, (d, lat) in named:
            if d <= 0:
                raise ConfigError(f"{key}: distance must be > 0, got {d!r}")
            try:
                contact_position(scene, self.sensor, d, lat)
            except ConfigError:
                raise ConfigError(f"{key}: a contact at [{d:g}, {lat:g}] m from sensor {self.sensor} lies outside the waveguide") from None
        return scene


def contact_position(scene: Scene, sensor: int, distance_m: float, lateral_m: float = 0.0) -> tuple[float, float]:
    """The point ``distance_m`` along sensor ``sensor``'s optical axis (and ``lateral_m`` to its left)."""
    s = scene.sensors[sensor]
    a = np.radians(s.direction_deg)
    x = s.position_m[0] + distance_m * np.cos(a) - lateral_m * np.sin(a)
    y = s.position_m[1] + distance_m * np.sin(a) + lateral_m * np.cos(a)
    if not scene.waveguide.contains(x, y):
        raise ConfigError(
            f"distance_m: a contact {distance_m:g} m in front of sensor {sensor} (lateral {lateral_m:g} m) lies outside the waveguide"
        )
    return float(x), float(y)


def indentation_force(targets_n, velocity_mm_s: float, p: Protocol, rng: np.random.Generator):
    """The true force at ``p.force_rate_hz`` for indentations to ``targets_n`` at ``velocity_mm_s``.

    Returns ``(t_s, force_n, segment)``: ``segment[i]`` is the index of the
    indentation sample ``i`` belongs to (-1 for the leading baseline).
    """
    dt = 1.0 / p.force_rate_hz
    k = p.stiffness_n_per_mm1p5
    parts, seg = [np.zeros(int(round(p.baseline_s / dt)))], [np.full(int(round(p.baseline_s / dt)), -1)]
    for j, f in enumerate(targets_n):
        depth = (f / k) ** (2.0 / 3.0)  # mm
        n_ramp = max(1, int(np.ceil(depth / velocity_mm_s / dt)))
        d_up = np.minimum(np.arange(1, n_ramp + 1) * velocity_mm_s * dt, depth)
        up = k * d_up**1.5
        hold = np.full(int(round(p.hold_s / dt)), f)
        down = up[::-1][1:]
        rest = np.zeros(int(round(p.rest_s / dt)) + 1)
        block = np.concatenate([up, hold, down, rest])
        parts.append(block)
        seg.append(np.full(block.size, j))
    force = np.concatenate(parts)
    return np.arange(force.size) * dt, force, np.concatenate(seg)


def lag(x, dt_s: float, tau_s: float):
    """First-order lag ``tau dy/dt = x - y`` (exact for piecewise-constant ``x``), from ``y = 0``."""
    a = float(-np.expm1(-dt_s / tau_s))

    def step(y, xi):
        y = y + a * (xi - y)
        return y, y

    _, y = jax.lax.scan(step, jnp.zeros((), jnp.float64 if jax.config.jax_enable_x64 else jnp.float32), jnp.asarray(x))
    return np.asarray(y, np.float64)


def touch_strength(force_n, p: Protocol):
    """The forward model's touch strength for a (lagged) force: saturating, 0 at 0 N."""
    return p.strength_max * -np.expm1(-np.maximum(force_n, 0.0) / p.strength_force_n)


def contact_radius(force_n, p: Protocol):
    """Radius of the deformed contact: sqrt(R d) of the indentation depth, capped at the indenter's radius."""
    depth_m = 1e-3 * (np.maximum(force_n, 0.0) / p.stiffness_n_per_mm1p5) ** (2.0 / 3.0)
    return np.clip(np.sqrt(p.indenter_radius_m * depth_m), 1e-3, p.indenter_radius_m)


def align_force(t_ref_s, f_ref, t_frames_s, exposure_s: float):
    """The reference force averaged over each frame's exposure window ``(t - exposure_s, t]``.

    This is how a 100 Hz force reference is put on the 9 Hz ToF frames: both see the
    same stretch of time. A window holding no reference sample takes the latest
    sample before the frame.
    """
    t_ref_s, f_ref, t_frames_s = (np.asarray(a, np.float64) for a in (t_ref_s, f_ref, t_frames_s))
    c = np.concatenate([[0.0], np.cumsum(f_ref)])
    hi = np.searchsorted(t_ref_s, t_frames_s, side="right")
    lo = np.searchsorted(t_ref_s, t_frames_s - exposure_s, side="right")
    n = hi - lo
    last = f_ref[np.clip(hi - 1, 0, len(f_ref) - 1)]
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(n > 0, (c[hi] - c[lo]) / np.maximum(n, 1), last)


def _frame_mean(t_ref_s, x, t_frames_s, exposure_s):
    return align_force(t_ref_s, x, t_frames_s, exposure_s)


_CHUNK = 256


@functools.lru_cache(maxsize=8)
def _renderer(scene: Scene, radius_m: float, dtype: str, n_contacts: int = 1):
    """A jitted (contact positions, chunk of frames) -> expected histograms function, compiled once per scene
    and number of contacts. Strength and radius are (frames, contacts)."""
    opts = ModelOptions(dtype=dtype)
    lx, ly = scene.waveguide.size_m
    touched = scene.replace(
        touches=tuple(Touch(position_m=(lx / 2, ly / 2 + 0.01 * k), radius_m=radius_m, strength=1.0) for k in range(n_contacts))
    )
    model = build_model(touched, opts)
    p0 = Params.from_scene(touched, opts.jnp_dtype)
    S, Z, _ = scene.shape

    def one(xy, s, r, o, a, g):
        q = p0.replace(
            touch_xy_m=xy,
            touch_strength=s,
            touch_radius_m=r,
            shadow_opacity=o,
            ambient_counts=jnp.full((S, Z), a),
            gain=p0.gain * g,
            crosstalk_counts=p0.crosstalk_counts * g,
        )
        return model(q)

    return jax.jit(jax.vmap(one, in_axes=(None, 0, 0, 0, 0, 0))), opts.jnp_dtype


def _render(scene: Scene, p: Protocol, xy, strength, radius, opacity, ambient, flatten, rng):
    """Photon-noisy histograms for per-frame contact and ambient states: (F, S, Z, B).

    Frames go through the vmapped forward model in fixed-size chunks, so it compiles once.
    Photon noise is drawn with NumPy (its Poisson sampler is ~10x faster than JAX's on CPU).
    """
    xy = np.atleast_2d(np.asarray(xy, np.float64))
    strength, radius = (np.asarray(v, np.float64).reshape(len(v), -1) for v in (strength, radius))
    f, dt = _renderer(scene, p.indenter_radius_m, p.dtype, xy.shape[0])
    xy = jnp.asarray(xy, dt)
    n = len(strength)
    pad = (-n) % _CHUNK
    args = [np.pad(np.asarray(v, np.float64), [(0, pad)] + [(0, 0)] * (np.ndim(v) - 1), mode="edge")
            for v in (strength, radius, opacity, ambient, flatten)]
    out = np.empty((n + pad, *scene.shape), np.float32)
    for i in range(0, n + pad, _CHUNK):
        sl = slice(i, i + _CHUNK)
        out[sl] = np.asarray(f(xy, *(jnp.asarray(a[sl], dt) for a in args)))
    lam = np.maximum(np.nan_to_num(out[:n].astype(np.float64), nan=0.0, posinf=0.0), 0.0)
    counts = rng.poisson(lam).astype(np.float64) if scene.noise.poisson else lam
    return np.minimum(counts, scene.sensor.saturation_counts).astype(np.float32)


def simulate_session(
    scene: Scene, p: Protocol, targets_n, velocity_mm_s: float, seed: int, *, split: str = "train", positions=None
) -> Capture:
    """One capture: a baseline, then indentations to ``targets_n`` at ``velocity_mm_s``, one ambient condition.

    ``positions``: the contacts' ``[distance, lateral]`` (default: the protocol's one
    position). With several contacts, ``targets_n`` holds one list of targets per contact;
    they are pressed at the same time, each to its own forces.
    """
    rng = np.random.default_rng(seed)
    positions = [(p.distance_m, p.lateral_m)] if positions is None else [tuple(q) for q in positions]
    targets = [list(targets_n)] if len(positions) == 1 else [list(t) for t in targets_n]
    if len(targets) != len(positions):
        raise ConfigError(f"{len(positions)} contacts need {len(positions)} lists of target forces")
    xys = [contact_position(scene, p.sensor, d, lat) for d, lat in positions]
    dt = 1.0 / p.force_rate_hz
    f_true = []
    for t in targets:
        _, f, _ = indentation_force(t, velocity_mm_s, p, rng)
        f_true.append(f)
    n_ref = max(f.size for f in f_true)
    f_true = [np.pad(f, (0, n_ref - f.size)) for f in f_true]
    t_ref = np.arange(n_ref) * dt
    f_lag = [lag(f, dt, p.lag_s) for f in f_true]
    f_meas = [f + p.force_noise_n * rng.standard_normal(f.size) for f in f_true]
    # Frames: the first one ends one exposure after the start.
    period = 1.0 / p.frame_rate_hz
    t_frames = np.arange(period, t_ref[-1] + 1e-9, period)
    lo, hi = p.ambient_counts_range
    a0 = float(np.exp(rng.uniform(np.log(max(lo, 1e-3)), np.log(max(hi, 1e-3))))) if hi > 0 else 0.0
    phase = rng.uniform(0, 2 * np.pi)
    amb_ref = a0 * (1.0 + p.ambient_drift * np.sin(2 * np.pi * t_ref / p.ambient_drift_period_s + phase))
    # What one frame integrates: the optical state averaged over its exposure.
    strength = np.stack([_frame_mean(t_ref, touch_strength(f, p), t_frames, period) for f in f_lag], 1)
    radius = np.stack([_frame_mean(t_ref, contact_radius(f, p), t_frames, period) for f in f_lag], 1)
    # A contact shadows what lies behind it only while it is there (several: the most pressed one's shadow).
    f_max = np.max(np.stack(f_lag), 0)
    opacity = scene.waveguide.shadow_opacity * _frame_mean(t_ref, -np.expm1(-np.maximum(f_max, 0) / 2.0), t_frames, period)
    ambient = _frame_mean(t_ref, amb_ref, t_frames, period)
    flatten = 1.0 / (1.0 + ambient / p.ambient_flattening_counts)
    hist = _render(scene, p, xys, strength, radius, opacity, ambient, flatten, rng)
    forces = [align_force(t_ref, f, t_frames, period) for f in f_meas]
    touches = np.stack(
        [np.stack([np.full(len(t_frames), xy[0]), np.full(len(t_frames), xy[1]), strength[:, k]], 1) for k, xy in enumerate(xys)],
        1,
    )
    s0 = scene.sensors[p.sensor].position_m
    truth = {
        "protocol": "seed001-indentation",
        "split": split,
        "velocity_mm_s": float(velocity_mm_s),
        "target_forces_n": [float(f) for f in targets[0]],
        "contact_xy_m": list(xys[0]),
        "distance_m": positions[0][0],
        "lateral_m": positions[0][1],
        "n_contacts": len(positions),
        "contacts": [
            {"distance_m": d, "lateral_m": lat, "xy_m": list(xy), "range_m": float(np.hypot(xy[0] - s0[0], xy[1] - s0[1])),
             "target_forces_n": [float(f) for f in t]}
            for (d, lat), xy, t in zip(positions, xys, targets)
        ],
        "sensor": p.sensor,
        "ambient_counts": a0,
        "baseline_frames": p.baseline_frames,
        "seed": seed,
        "parameters": to_dict(p),
    }
    if len(positions) > 1:
        truth["contact_forces_n"] = [np.round(f, 3).tolist() for f in forces]
    return Capture(
        histograms=hist,
        timestamps=t_frames,
        scene=scene,
        source="simulated",
        force=forces[0],
        truth_touches=touches,
        truth=truth,
    )


def generate(
    p: Protocol, out_dir: str | Path | None = None, *, progress: bool = False, overwrite: bool = False
) -> dict[str, list]:
    """Simulate the whole protocol: ``{"train": [...], "test": [...]}`` captures (or paths, with ``out_dir``).

    Training: for each velocity and repetition one capture with every training
    force (in a shuffled order). Test: for each velocity
    ``test_forces_per_velocity`` random forces in ``test_force_range_n`` spread
    over ``test_captures_per_velocity`` captures. Every capture has its own
    ambient light. With ``out_dir`` the captures are written there as
    ``train_v<v>_r<i>.h5`` / ``test_v<v>_r<i>.h5`` with a ``protocol.json``, and
    the paths are returned.
    """
    from tqdm import tqdm

    scene = p.load_scene()
    rng = np.random.default_rng(p.seed)
    many = len(p.train_positions) > 1 or p.unseen_positions_m or p.two_contacts_m
    jobs = []  # (split, velocity, repetition, targets, positions, file stem)

    def stem(split, i, v, r):
        return f"{split}_p{i}_v{v:g}_r{r}" if many else f"{split}_v{v:g}_r{r}"

    def test_jobs(split, i, pos):
        for v in p.velocities_mm_s:
            forces = np.round(rng.uniform(*p.test_force_range_n, p.test_forces_per_velocity), 1)
            for r, chunk in enumerate(np.array_split(forces, p.test_captures_per_velocity)):
                if len(chunk):
                    jobs.append((split, v, r, list(chunk), [pos], stem(split, i, v, r)))

    for i, pos in enumerate(p.train_positions):
        for v in p.velocities_mm_s:
            for r in range(p.repetitions):
                jobs.append(("train", v, r, list(rng.permutation(np.asarray(p.train_forces_n, float))), [pos], stem("train", i, v, r)))
    for i, pos in enumerate(p.train_positions):
        test_jobs("test", i, pos)
    for i, pos in enumerate(p.unseen_positions_m):
        test_jobs("unseen", i, pos)
    for i, pair in enumerate(p.two_contacts_m):
        for v in p.velocities_mm_s:
            n = max(p.test_forces_per_velocity // p.test_captures_per_velocity, 1)
            forces = [list(np.round(rng.uniform(*p.test_force_range_n, n), 1)) for _ in pair]
            jobs.append(("two_contacts", v, 0, forces, list(pair), stem("two_contacts", i, v, 0)))
    out: dict[str, list] = {"train": [], "test": [], "unseen": [], "two_contacts": []}
    if out_dir is not None:
        out_dir = Path(out_dir)
        out_dir.mkdir(parents=True, exist_ok=True)
        (out_dir / "protocol.json").write_text(json.dumps(to_dict(p), indent=2))
    seeds = rng.integers(0, 2**31 - 1, len(jobs))
    for (split, v, r, forces, pos, name), s in zip(tqdm(jobs, desc="simulating captures", disable=not progress), seeds):
        cap = simulate_session(scene, p, forces if len(pos) > 1 else forces, v, int(s), split=split, positions=pos)
        if out_dir is None:
            out[split].append(cap)
        else:
            path = out_dir / f"{name}.h5"
            write_capture(path, cap, overwrite=overwrite)
            out[split].append(path)
    return {k: v for k, v in out.items() if v or k in ("train", "test")}


def protocol_from_dict(data: dict, source: str = "protocol") -> Protocol:
    try:
        return from_dict(Protocol, data)
    except ConfigError as e:
        raise ConfigError(f"{source}: {e}") from None


def protocol_key(p: Protocol) -> str:
    """A short stable hash of the protocol (names cached data)."""
    import hashlib

    return hashlib.sha1(json.dumps(dataclasses.asdict(p), sort_keys=True).encode()).hexdigest()[:12]
