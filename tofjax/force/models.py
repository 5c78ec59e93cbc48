"""The MLPs of seed 001 (Fig. 11-13) in equinox, and their training with optax.

Every model takes one input vector (the variant's features, see
:func:`tofjax.force.features.select`) and returns a normalised force. Two-branch
models split that vector: the first ``n_d`` values (the response, or the response
and its derivative) go through one branch, the rest (the baseline) through the
other.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass
from typing import Callable

import equinox as eqx
import jax
import jax.numpy as jnp
import optax

from ..config import ConfigError

__all__ = ["ForceMLP", "MLPSpec", "TrainOptions", "TrainResult", "build_mlp", "mlp_spec", "operations", "train_mlp"]


@dataclass(frozen=True)
class MLPSpec:
    """An architecture: branch widths, shared hidden widths and where dropout goes."""

    n_d: int  # inputs of the response branch
    n_b: int  # inputs of the baseline branch (0: single input)
    d_width: int
    b_width: int
    hidden: tuple[int, ...]
    #: Dropout after the first layer ("first", seed 001 Fig. 11) or after the last hidden layer ("last", Fig. 12-13).
    dropout_at: str
    dropout: float

    def to_json(self) -> dict:
        return dict(self.__dict__, hidden=list(self.hidden))

    @classmethod
    def from_json(cls, d: dict) -> "MLPSpec":
        return cls(**dict(d, hidden=tuple(d["hidden"])))


def mlp_spec(
    kind: str, variant: str, n: int, *, dropout: float = 0.3, deep_hidden=(128, 128, 64, 32), extra: int = 0
) -> MLPSpec:
    """The architecture of seed 001 for ``kind`` (``mlp`` or ``deep_mlp``) and input ``variant``.

    ``n`` is the number of values in the contact window (4 beams x 5 bins = 20); ``extra``
    context inputs (the contact's position, the ambient level) join the baseline branch
    (the only branch of the single-input MLP).
    """
    if kind == "mlp":
        if variant == "single":
            return MLPSpec(n + extra, 0, 64, 0, (32,), "first", dropout)
        if variant == "dual":
            return MLPSpec(n, n + extra, 32, 32, (32,), "last", dropout)
        return MLPSpec(2 * n, n + extra, 64, 32, (32,), "last", dropout)
    if kind == "deep_mlp":
        n_in = {"single": n, "dual": 2 * n, "derivative": 3 * n}[variant] + extra
        return MLPSpec(n_in, 0, deep_hidden[0], 0, tuple(deep_hidden[1:]), "first", dropout)
    raise ConfigError(f"model.kind: {kind!r} is not an MLP")


class ForceMLP(eqx.Module):
    """``model(x, key=None) -> normalised force``; dropout only when a key is given (training)."""

    d_layer: eqx.nn.Linear
    b_layer: eqx.nn.Linear | None
    layers: tuple[eqx.nn.Linear, ...]
    out: eqx.nn.Linear
    spec: MLPSpec = eqx.field(static=True)

    def __call__(self, x, key=None):
        s = self.spec
        h = jax.nn.relu(self.d_layer(x[: s.n_d]))
        if self.b_layer is not None:
            h = jnp.concatenate([h, jax.nn.relu(self.b_layer(x[s.n_d : s.n_d + s.n_b]))])
        keys = [None] * 2 if key is None else list(jax.random.split(key, 2))
        if s.dropout_at == "first":
            h = _dropout(h, s.dropout, keys[0])
        for layer in self.layers:
            h = jax.nn.relu(layer(h))
        if s.dropout_at == "last":
            h = _dropout(h, s.dropout, keys[1])
        return self.out(h)[0]


def _dropout(h, p, key):
    if key is None or p == 0:
        return h
    keep = jax.random.bernoulli(key, 1.0 - p, h.shape)
    return jnp.where(keep, h / (1.0 - p), 0.0)


def build_mlp(spec: MLPSpec, key, dtype=jnp.float32) -> ForceMLP:
    k = list(jax.random.split(key, 3 + len(spec.hidden)))
    d_layer = eqx.nn.Linear(spec.n_d, spec.d_width, key=k[0], dtype=dtype)
    b_layer = eqx.nn.Linear(spec.n_b, spec.b_width, key=k[1], dtype=dtype) if spec.n_b else None
    widths = [spec.d_width + (spec.b_width if spec.n_b else 0), *spec.hidden]
    layers = tuple(eqx.nn.Linear(a, b, key=k[2 + i], dtype=dtype) for i, (a, b) in enumerate(zip(widths[:-1], widths[1:])))
    out = eqx.nn.Linear(widths[-1], 1, key=k[-1], dtype=dtype)
    return ForceMLP(d_layer, b_layer, layers, out, spec)


def operations(spec: MLPSpec) -> int:
    """Arithmetic operations of one forward pass: 2 per weight (multiply, add), 1 per bias and ReLU."""
    ops = 0
    widths = [spec.d_width + (spec.b_width if spec.n_b else 0), *spec.hidden, 1]
    for a, b in [(spec.n_d, spec.d_width)] + ([(spec.n_b, spec.b_width)] if spec.n_b else []):
        ops += 2 * a * b + 2 * b
    for a, b in zip(widths[:-1], widths[1:]):
        ops += 2 * a * b + 2 * b
    return ops


@dataclass(frozen=True)
class TrainOptions:
    """How an MLP is trained.

    **Arguments:**

    - ``epochs``: most passes over the training split (seed 001: 300).
    - ``batch_size``: samples per optimiser step.
    - ``learning_rate``: peak learning rate of Adam(W).
    - ``schedule``: ``constant``, ``cosine`` (decays to ``final_lr_fraction``) or ``exponential``.
    - ``warmup_epochs``: linear warm-up.
    - ``weight_decay``: AdamW decoupled weight decay.
    - ``loss``: ``mse`` or ``huber`` on the normalised force.
    - ``patience``: stop after this many epochs without a better validation loss; the
      best model is kept. 0 disables early stopping.
    """

    epochs: int = 300
    batch_size: int = 64
    learning_rate: float = 1e-3
    schedule: str = "cosine"
    final_lr_fraction: float = 0.02
    warmup_epochs: int = 0
    weight_decay: float = 1e-5
    loss: str = "mse"
    patience: int = 100

    def __post_init__(self):
        if self.epochs < 1 or self.batch_size < 1:
            raise ConfigError("epochs and batch_size: must be >= 1")
        if not self.learning_rate > 0:
            raise ConfigError(f"learning_rate: must be > 0, got {self.learning_rate!r}")
        if self.schedule not in ("constant", "cosine", "exponential"):
            raise ConfigError(f"schedule: must be constant, cosine or exponential, got {self.schedule!r}")
        if self.loss not in ("mse", "huber"):
            raise ConfigError(f"loss: must be mse or huber, got {self.loss!r}")
        if self.patience < 0 or self.warmup_epochs < 0 or self.weight_decay < 0:
            raise ConfigError("patience, warmup_epochs and weight_decay: must be >= 0")


def _schedule(o: TrainOptions, steps_per_epoch: int):
    total = o.epochs * steps_per_epoch
    warm = o.warmup_epochs * steps_per_epoch
    if o.schedule == "constant":
        main = optax.constant_schedule(o.learning_rate)
    elif o.schedule == "cosine":
        main = optax.cosine_decay_schedule(o.learning_rate, max(total - warm, 1), alpha=o.final_lr_fraction)
    else:
        main = optax.exponential_decay(o.learning_rate, max(total - warm, 1), o.final_lr_fraction)
    if warm:
        return optax.join_schedules([optax.linear_schedule(0.0, o.learning_rate, warm), main], [warm])
    return main


@dataclass
class TrainResult:
    model: ForceMLP
    best_epoch: int
    best_val_loss: float
    epochs_run: int
    history: list[dict]
    seconds: float


def train_mlp(
    model: ForceMLP,
    x_train,
    y_train,
    x_val,
    y_val,
    options: TrainOptions = TrainOptions(),
    *,
    key,
    on_epoch: Callable[[dict], None] | None = None,
    progress: bool = False,
) -> TrainResult:
    """Train ``model`` on normalised inputs and targets; keep the best model on the validation split.

    One epoch (shuffle, every batch through ``lax.scan``, the validation loss) is one
    jitted call. ``on_epoch`` gets each epoch's row (epoch, train/val loss, learning
    rate, seconds) as it finishes: runs write it to ``metrics.csv``.
    """
    from tqdm import tqdm

    dtype = jnp.float32
    xt, yt = jnp.asarray(x_train, dtype), jnp.asarray(y_train, dtype)
    xv, yv = jnp.asarray(x_val, dtype), jnp.asarray(y_val, dtype)
    n = xt.shape[0]
    bs = min(options.batch_size, n)
    steps = n // bs
    sched = _schedule(options, steps)
    opt = optax.adamw(sched, weight_decay=options.weight_decay)
    params, static = eqx.partition(model, eqx.is_inexact_array)
    opt_state = opt.init(params)

    def loss_fn(p, x, y, k):
        m = eqx.combine(p, static)
        pred = jax.vmap(m)(x, jax.random.split(k, x.shape[0]))
        r = pred - y
        if options.loss == "huber":
            return jnp.mean(optax.huber_loss(r, delta=0.05))
        return jnp.mean(r**2)

    @jax.jit
    def epoch(p, s, k):
        kp, kd = jax.random.split(k)
        idx = jax.random.permutation(kp, n)[: steps * bs].reshape(steps, bs)

        def step(carry, inp):
            p, s = carry
            i, kk = inp
            loss, g = jax.value_and_grad(loss_fn)(p, xt[i], yt[i], kk)
            u, s = opt.update(g, s, p)
            return (eqx.apply_updates(p, u), s), loss

        (p, s), losses = jax.lax.scan(step, (p, s), (idx, jax.random.split(kd, steps)))
        m = eqx.combine(p, static)
        val = jnp.mean((jax.vmap(m)(xv) - yv) ** 2)
        return p, s, jnp.mean(losses), val

    t0 = time.perf_counter()
    best = (math.inf, 0, params)
    history = []
    keys = jax.random.split(key, options.epochs)
    bar = tqdm(range(options.epochs), desc="training", disable=not progress, leave=False)
    e = 0
    for e in bar:
        params, opt_state, tl, vl = epoch(params, opt_state, keys[e])
        tl, vl = float(tl), float(vl)
        row = {
            "epoch": e + 1,
            "train_loss": tl,
            "val_loss": vl,
            "learning_rate": float(sched((e + 1) * steps)),
            "seconds": time.perf_counter() - t0,
        }
        history.append(row)
        if on_epoch is not None:
            on_epoch(row)
        if vl < best[0]:
            best = (vl, e + 1, params)
        bar.set_postfix(val=f"{vl:.2e}", best=best[1])
        if options.patience and e + 1 - best[1] >= options.patience:
            break
    return TrainResult(
        model=eqx.combine(best[2], static),
        best_epoch=best[1],
        best_val_loss=best[0],
        epochs_run=e + 1,
        history=history,
        seconds=time.perf_counter() - t0,
    )
