"""The residual random forest (seed 001 Eq. 7): scikit-learn fits it, JAX or NumPy evaluates it.

A fitted ``RandomForestRegressor`` (every tree at most ``depth`` levels) becomes
*complete* binary trees in heap order, packed into flat arrays: ``feature`` and
``threshold`` of the ``2^depth - 1`` split nodes of every tree, ``value`` of its
``2^depth`` leaves. Node ``i``'s children are ``2i + 1`` and ``2i + 2``, so a
prediction walks every tree at once for exactly ``depth`` levels::

    node = 2 * node + 1 + (x[feature[node]] > threshold[node])

with no child arrays, no recursion and no Python per tree. A scikit-learn leaf above
the last level becomes a split that always goes left (threshold +inf) over a subtree
whose leaves all hold its value.

scikit-learn compares ``float32(x) <= threshold`` with float64 thresholds. The
arrays store each threshold rounded *down* to float32, for which
``x <= floor32(t)`` equals ``x <= t`` for every float32 ``x``: the packed forest
takes the same branches as scikit-learn's, bit for bit.

Format version 2 (this layout). Version 1 (padded per-tree node arrays with
``left``/``right``) is refused on loading with one line: retrain the run.
"""

from __future__ import annotations

from dataclasses import dataclass

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from ..config import ConfigError
from ..errors import UserError

__all__ = [
    "FOREST_FORMAT_VERSION",
    "ForestArrays",
    "ForestFormatError",
    "ForestOptions",
    "fit_forest",
    "forest_operations",
    "forest_predict",
    "forest_predict_numpy",
    "forest_to_arrays",
]

FOREST_FORMAT_VERSION = 2
#: Deepest packed tree: 2^14 leaves per tree is already 6.5 MB for 100 trees.
MAX_DEPTH = 14


class ForestFormatError(UserError):
    """A stored forest in another layout than this tofjax's."""


@dataclass(frozen=True)
class ForestOptions:
    """The residual forest (seed 001: 100 trees, bootstrap).

    ``max_depth`` is also the packed trees' depth, the number of levels every prediction
    walks (at most 14); 8 keeps one MLP + forest prediction under 100 us.
    ``min_samples_leaf`` bounds the leaves; ``n_jobs`` is scikit-learn's parallelism.
    """

    enabled: bool = True
    trees: int = 100
    bootstrap: bool = True
    max_depth: int = 8
    min_samples_leaf: int = 5
    #: Fraction of features tried at each split (0.5: twice as fast as all, and less correlated trees).
    max_features: float = 0.5
    n_jobs: int = 2

    def __post_init__(self):
        if self.trees < 1 or self.max_depth < 1 or self.min_samples_leaf < 1:
            raise ConfigError("trees, max_depth and min_samples_leaf: must be >= 1")
        if self.max_depth > MAX_DEPTH:
            raise ConfigError(f"max_depth: at most {MAX_DEPTH} (the packed trees are complete), got {self.max_depth!r}")
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
    """A forest as complete heap-ordered trees, flattened over the trees.

    ``feature``, ``threshold``: (trees * (2^depth - 1),) split nodes; ``value``:
    (trees * 2^depth,) leaves.
    """

    feature: jax.Array  # int32
    threshold: jax.Array  # float32, rounded down; +inf: always left
    value: jax.Array  # float32 leaf values
    trees: int = eqx.field(static=True)
    depth: int = eqx.field(static=True)

    def to_numpy(self) -> dict:
        return {
            "feature": np.asarray(self.feature),
            "threshold": np.asarray(self.threshold),
            "value": np.asarray(self.value),
            "trees": np.asarray(self.trees),
            "depth": np.asarray(self.depth),
            "format_version": np.asarray(FOREST_FORMAT_VERSION),
        }

    @classmethod
    def from_numpy(cls, d, source: str = "forest") -> "ForestArrays":
        keys = set(getattr(d, "files", d))
        version = int(d["format_version"]) if "format_version" in keys else 1
        if version != FOREST_FORMAT_VERSION:
            raise ForestFormatError(
                f"{source}: forest format version {version} (this tofjax reads version {FOREST_FORMAT_VERSION}, "
                "complete packed trees); retrain the run with `tofjax train`"
            )
        trees, depth = int(d["trees"]), int(d["depth"])
        f, t, v = (np.asarray(d[k]) for k in ("feature", "threshold", "value"))
        if not 1 <= depth <= MAX_DEPTH or f.shape != (trees * (2**depth - 1),) or t.shape != f.shape or v.shape != (trees * 2**depth,):
            raise ForestFormatError(f"{source}: damaged forest (array sizes do not match {trees} trees of depth {depth})")
        return cls(jnp.asarray(f, jnp.int32), jnp.asarray(t, jnp.float32), jnp.asarray(v, jnp.float32), trees, depth)

    def numpy(self) -> "NumpyForest":
        return NumpyForest(np.asarray(self.feature), np.asarray(self.threshold), np.asarray(self.value), self.trees, self.depth)


@dataclass(frozen=True)
class NumpyForest:
    feature: np.ndarray
    threshold: np.ndarray
    value: np.ndarray
    trees: int
    depth: int


def _floor32(t: np.ndarray) -> np.ndarray:
    t32 = t.astype(np.float32)
    return np.where(t32.astype(np.float64) > t, np.nextafter(t32, np.float32(-np.inf)), t32).astype(np.float32)


def forest_to_arrays(rf, depth: int | None = None) -> ForestArrays:
    """Pack a fitted ``RandomForestRegressor`` (single output) into complete trees of ``depth`` levels
    (default: the deepest tree's depth; at least 1)."""
    trees = [e.tree_ for e in rf.estimators_]
    deepest = max(t.max_depth for t in trees)
    depth = max(1, deepest if depth is None else depth)
    if deepest > depth:
        raise ValueError(f"a tree is {deepest} levels deep, more than the packed depth {depth}")
    if depth > MAX_DEPTH:
        raise ValueError(f"packed depth {depth} is more than {MAX_DEPTH}")
    T, n_split, n_leaf = len(trees), 2**depth - 1, 2**depth
    feature = np.zeros((T, n_split), np.int32)
    threshold = np.full((T, n_split), np.inf, np.float32)
    value = np.zeros((T, n_leaf), np.float32)
    for i, t in enumerate(trees):
        stack = [(0, 0, 0)]  # (sklearn node, heap node, level)
        while stack:
            s, h, lev = stack.pop()
            if t.children_left[s] == -1:  # a leaf: every heap leaf below h holds its value
                span = 2 ** (depth - lev)
                first = (h + 1) * span - 1 - n_split
                value[i, first : first + span] = t.value[s, 0, 0]
                continue
            feature[i, h] = t.feature[s]
            threshold[i, h] = _floor32(np.asarray([t.threshold[s]]))[0]
            stack.append((t.children_left[s], 2 * h + 1, lev + 1))
            stack.append((t.children_right[s], 2 * h + 2, lev + 1))
    return ForestArrays(
        jnp.asarray(feature.reshape(-1)), jnp.asarray(threshold.reshape(-1)), jnp.asarray(value.reshape(-1)), T, depth
    )


def forest_predict(forest: ForestArrays, x):
    """Mean leaf value over the trees for one input ``x`` (features,); vmap it for batches.

    All trees walk together, one level per step (unrolled: the depth is fixed): two
    gathers and a comparison per level.
    """
    x = jnp.asarray(x).astype(jnp.float32)
    T, D = forest.trees, forest.depth
    n_split = 2**D - 1
    base = jnp.arange(T, dtype=jnp.int32) * n_split
    node = jnp.zeros(T, jnp.int32)
    for _ in range(D):
        i = base + node
        node = 2 * node + 1 + (x[forest.feature[i]] > forest.threshold[i]).astype(jnp.int32)
    leaf = jnp.arange(T, dtype=jnp.int32) * (2**D) + node - n_split
    return jnp.mean(forest.value[leaf])


def forest_predict_numpy(forest: NumpyForest, x: np.ndarray) -> float:
    """:func:`forest_predict` in NumPy for one input (the fast path of one warm prediction)."""
    T, D = forest.trees, forest.depth
    n_split = 2**D - 1
    base = np.arange(T) * n_split
    node = np.zeros(T, np.intp)
    f, t = forest.feature, forest.threshold
    x = np.asarray(x, np.float32)
    for _ in range(D):
        i = base + node
        node = 2 * node + 1 + (x[f[i]] > t[i])
    return float(forest.value[np.arange(T) * (2**D) + node - n_split].mean())


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
