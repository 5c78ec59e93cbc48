"""The residual random forest (seed 001 Eq. 7): scikit-learn fits it, JAX evaluates it.

A fitted ``RandomForestRegressor`` becomes padded arrays (trees x nodes); a
prediction walks every tree at once for a fixed number of levels (the deepest
tree's depth), leaves pointing to themselves, so the whole MLP + forest
predictor is one jitted function with no Python in the loop.

scikit-learn compares ``float32(x) <= threshold`` with float64 thresholds. The
arrays store each threshold rounded *down* to float32, for which
``x <= floor32(t)`` equals ``x <= t`` for every float32 ``x``: the JAX forest
takes the same branches as scikit-learn's, bit for bit.
"""

from __future__ import annotations

from dataclasses import dataclass

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from ..config import ConfigError

__all__ = ["ForestArrays", "ForestOptions", "fit_forest", "forest_operations", "forest_predict", "forest_to_arrays"]


@dataclass(frozen=True)
class ForestOptions:
    """The residual forest (seed 001: 100 trees, bootstrap).

    ``max_depth`` and ``min_samples_leaf`` bound its size (and the saved model's);
    ``n_jobs`` is scikit-learn's parallelism.
    """

    enabled: bool = True
    trees: int = 100
    bootstrap: bool = True
    max_depth: int = 20
    min_samples_leaf: int = 5
    #: Fraction of features tried at each split (0.5: twice as fast as all, and less correlated trees).
    max_features: float = 0.5
    n_jobs: int = 2

    def __post_init__(self):
        if self.trees < 1 or self.max_depth < 1 or self.min_samples_leaf < 1:
            raise ConfigError("trees, max_depth and min_samples_leaf: must be >= 1")
        if not 0 < self.max_features <= 1:
            raise ConfigError(f"max_features: must be in (0, 1], got {self.max_features!r}")


def fit_forest(x, residual, options: ForestOptions, seed: int = 0):
    """A scikit-learn random forest fitted to ``residual`` (N) from features ``x``."""
    from sklearn.ensemble import RandomForestRegressor

    rf = RandomForestRegressor(
        n_estimators=options.trees,
        bootstrap=options.bootstrap,
        max_depth=options.max_depth,
        min_samples_leaf=options.min_samples_leaf,
        max_features=options.max_features,
        n_jobs=options.n_jobs,
        random_state=seed,
    )
    rf.fit(np.asarray(x, np.float32), np.asarray(residual, np.float64))
    return rf


class ForestArrays(eqx.Module):
    """A forest as arrays, shape (trees, nodes); leaves have ``left == right == self``."""

    feature: jax.Array  # int32
    threshold: jax.Array  # float32, rounded down
    left: jax.Array  # int32
    right: jax.Array  # int32
    value: jax.Array  # float32 leaf values
    depth: int = eqx.field(static=True)

    @property
    def trees(self) -> int:
        return int(self.feature.shape[0])

    def to_numpy(self) -> dict:
        return {k: np.asarray(getattr(self, k)) for k in ("feature", "threshold", "left", "right", "value")} | {
            "depth": np.asarray(self.depth)
        }

    @classmethod
    def from_numpy(cls, d) -> "ForestArrays":
        return cls(*(jnp.asarray(d[k]) for k in ("feature", "threshold", "left", "right", "value")), int(d["depth"]))


def _floor32(t: np.ndarray) -> np.ndarray:
    t32 = t.astype(np.float32)
    return np.where(t32.astype(np.float64) > t, np.nextafter(t32, np.float32(-np.inf)), t32).astype(np.float32)


def forest_to_arrays(rf) -> ForestArrays:
    """Convert a fitted ``RandomForestRegressor`` (single output) to :class:`ForestArrays`."""
    trees = [e.tree_ for e in rf.estimators_]
    n = max(t.node_count for t in trees)
    T = len(trees)
    feature = np.zeros((T, n), np.int32)
    threshold = np.full((T, n), np.inf, np.float32)
    idx = np.arange(n, dtype=np.int32)
    left = np.tile(idx, (T, 1))
    right = np.tile(idx, (T, 1))
    value = np.zeros((T, n), np.float32)
    for i, t in enumerate(trees):
        m = t.node_count
        leaf = t.children_left[:m] == -1
        feature[i, :m] = np.where(leaf, 0, t.feature[:m])
        threshold[i, :m] = np.where(leaf, np.float32(np.inf), _floor32(t.threshold[:m]))
        left[i, :m] = np.where(leaf, idx[:m], t.children_left[:m])
        right[i, :m] = np.where(leaf, idx[:m], t.children_right[:m])
        value[i, :m] = t.value[:m, 0, 0]
    depth = max(t.max_depth for t in trees)
    return ForestArrays(*(jnp.asarray(a) for a in (feature, threshold, left, right, value)), depth)


def forest_predict(forest: ForestArrays, x):
    """Mean leaf value over the trees for one input ``x`` (features,); vmap it for batches.

    The trees are walked together, one level per step, on the flattened node arrays
    (one 1-D gather per array and level; unrolled, as the depth is fixed).
    """
    x = jnp.asarray(x).astype(jnp.float32)
    T, N = forest.feature.shape
    offset = jnp.arange(T, dtype=jnp.int32) * N
    feature, threshold = forest.feature.reshape(-1), forest.threshold.reshape(-1)
    left, right = (forest.left + offset[:, None]).reshape(-1), (forest.right + offset[:, None]).reshape(-1)
    node = offset
    for _ in range(forest.depth):
        node = jnp.where(x[feature[node]] <= threshold[node], left[node], right[node])
    return jnp.mean(forest.value.reshape(-1)[node])


def forest_operations(rf) -> int:
    """Operations of one prediction: one comparison per level visited (the mean leaf depth), one add per tree."""
    ops = 0
    for e in rf.estimators_:
        t = e.tree_
        depth = np.zeros(t.node_count, int)
        for i in range(t.node_count):
            for c in (t.children_left[i], t.children_right[i]):
                if c != -1:
                    depth[c] = depth[i] + 1
        leaf = t.children_left == -1
        w = t.n_node_samples[leaf]
        ops += float((depth[leaf] * w).sum() / w.sum()) + 1
    return int(round(ops))
