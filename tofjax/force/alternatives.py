"""The alternatives of seed 001 Table I: nonlinear regression, SVR and gradient boosting (scikit-learn).

(The deep MLP is an equinox model, :func:`tofjax.force.models.mlp_spec` with ``kind = "deep_mlp"``.)
Each is fitted on the same normalised features and targets as the MLPs and
reports its arithmetic operations per prediction.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..config import ConfigError

__all__ = ["GBOptions", "NonlinearOptions", "SVROptions", "fit_alternative"]


@dataclass(frozen=True)
class NonlinearOptions:
    """Polynomial regression: all monomials up to ``degree``, ridge-regularised by ``alpha``."""

    degree: int = 2
    alpha: float = 1e-4

    def __post_init__(self):
        if self.degree < 1 or self.alpha < 0:
            raise ConfigError("nonlinear: degree must be >= 1 and alpha >= 0")


@dataclass(frozen=True)
class SVROptions:
    """Epsilon-SVR with an RBF kernel. Its fit is quadratic in the samples: ``max_train_samples`` caps them."""

    c: float = 10.0
    epsilon: float = 0.005
    gamma: float = 0.0  # 0: scikit-learn's "scale"
    max_train_samples: int = 6000

    def __post_init__(self):
        if self.c <= 0 or self.epsilon < 0 or self.gamma < 0 or self.max_train_samples < 10:
            raise ConfigError("svr: c > 0, epsilon >= 0, gamma >= 0, max_train_samples >= 10")


@dataclass(frozen=True)
class GBOptions:
    """Histogram gradient boosting of shallow trees (early stopping on the validation split)."""

    iterations: int = 1000
    learning_rate: float = 0.1
    max_leaf_nodes: int = 31
    max_depth: int = 6

    def __post_init__(self):
        if self.iterations < 1 or self.learning_rate <= 0 or self.max_leaf_nodes < 2 or self.max_depth < 1:
            raise ConfigError("gb: iterations >= 1, learning_rate > 0, max_leaf_nodes >= 2, max_depth >= 1")


def fit_alternative(kind: str, options, x, y, x_val, y_val, seed: int = 0):
    """Fit ``kind`` (``nonlinear``, ``svr``, ``gb``); returns ``(estimator, operations per prediction)``."""
    x = np.asarray(x, np.float64)
    y = np.asarray(y, np.float64)
    n_in = x.shape[1]
    if kind == "nonlinear":
        from sklearn.linear_model import Ridge
        from sklearn.pipeline import make_pipeline
        from sklearn.preprocessing import PolynomialFeatures

        est = make_pipeline(PolynomialFeatures(options.degree), Ridge(alpha=options.alpha))
        est.fit(x, y)
        n_terms = est[0].n_output_features_
        # Monomials by products of previous ones (one multiply each), then a dot product.
        return est, int(n_terms + 2 * n_terms)
    if kind == "svr":
        from sklearn.svm import SVR

        rng = np.random.default_rng(seed)
        if len(x) > options.max_train_samples:
            idx = rng.choice(len(x), options.max_train_samples, replace=False)
            x, y = x[idx], y[idx]
        est = SVR(C=options.c, epsilon=options.epsilon, gamma=options.gamma or "scale", kernel="rbf")
        est.fit(x, y)
        n_sv = est.support_vectors_.shape[0]
        # Per support vector: squared distance (3 n), exp (~10), multiply-add (2).
        return est, int(n_sv * (3 * n_in + 12))
    if kind == "gb":
        from sklearn.ensemble import HistGradientBoostingRegressor

        est = HistGradientBoostingRegressor(
            max_iter=options.iterations,
            learning_rate=options.learning_rate,
            max_leaf_nodes=options.max_leaf_nodes,
            max_depth=options.max_depth,
            early_stopping=True,
            n_iter_no_change=30,
            random_state=seed,
        )
        if _supports_xval():  # scikit-learn >= 1.6: stop on our validation split
            est.set_params(validation_fraction=None)
            est.fit(x, y, X_val=np.asarray(x_val, np.float64), y_val=np.asarray(y_val, np.float64))
        else:
            est.fit(x, y)
        depth = 0.0
        for (pred,) in est._predictors:
            nodes = pred.nodes
            leaf = nodes["is_leaf"].astype(bool)
            depth += float(nodes["depth"][leaf].mean()) + 1
        return est, int(round(depth))
    raise ConfigError(f"model.kind: unknown alternative {kind!r}")


def _supports_xval() -> bool:
    import inspect

    from sklearn.ensemble import HistGradientBoostingRegressor

    return "X_val" in inspect.signature(HistGradientBoostingRegressor.fit).parameters
