"""Gaussian-mixture pose prior in the SMPLify ``gmm_08`` layout.

The prior is a dict: ``means`` (K, 69), ``covars`` (K, 69, 69), ``weights`` (K,), float64; the
69 dims are the SMPL body pose (axis-angle, radians) without the global orientation.
:class:`GMMPosePrior` evaluates -log sum_k w_k N(pose; mu_k, Sigma_k) (the paper's form) with a
log-sum-exp. log det Sigma_k is often around -350, so determinants are never formed: the
Cholesky factors of the precisions and the log-determinants are computed in float64 once.
"""

from __future__ import annotations

import functools

import numpy as np
import torch
from torch import Tensor

from tasks.body.poses import sample_plausible_poses


def _log_gauss(X: np.ndarray, means: np.ndarray, prec_chol: np.ndarray) -> np.ndarray:
    """(N, K) log N(x_n; mu_k, Sigma_k) given Cholesky factors L_k of the precisions (P = L L^T)."""
    d = X.shape[1]
    out = np.empty((X.shape[0], means.shape[0]))
    for k in range(means.shape[0]):
        y = (X - means[k]) @ prec_chol[k]
        half_logdet_prec = np.log(np.diag(prec_chol[k])).sum()
        out[:, k] = -0.5 * (y * y).sum(1) + half_logdet_prec - 0.5 * d * np.log(2 * np.pi)
    return out


def _precision_cholesky(covars: np.ndarray) -> np.ndarray:
    """(K, d, d) covariances -> (K, d, d) lower factors L with L L^T = Sigma^-1."""
    out = np.empty_like(covars)
    eye = np.eye(covars.shape[1])
    for k, S in enumerate(covars):
        C = np.linalg.cholesky(S)  # S = C C^T  ->  S^-1 = C^-T C^-1 = L L^T with L = C^-T
        out[k] = np.linalg.solve(C, eye).T
    return out


def fit_pose_prior(
    poses: np.ndarray,
    n_components: int = 8,
    seed: int = 0,
    reg_covar: float = 1e-4,
    n_iter: int = 60,
    tol: float = 1e-5,
) -> dict[str, np.ndarray]:
    """Fit a full-covariance GMM to poses (N, 69) by EM (k-means++ start, ``reg_covar`` added to
    every covariance diagonal so all are well conditioned). Deterministic for a seed.

    Returns the gmm_08 dict: means (K, 69), covars (K, 69, 69), weights (K,), float64.
    """
    X = np.asarray(poses, dtype=np.float64)
    if X.ndim != 2 or X.shape[0] < n_components * 2:
        raise ValueError(
            f"fit_pose_prior: expected (N >= {2 * n_components}, d) poses, got {X.shape}"
        )
    if not np.all(np.isfinite(X)):
        raise ValueError("fit_pose_prior: poses contain non-finite values")
    N, d = X.shape
    rng = np.random.default_rng(seed)
    # k-means++ seeding, then a few Lloyd steps for the initial responsibilities.
    centers = [X[rng.integers(N)]]
    for _ in range(1, n_components):
        d2 = np.min(((X[:, None, :] - np.array(centers)[None]) ** 2).sum(-1), axis=1)
        centers.append(X[rng.choice(N, p=d2 / d2.sum())])
    C = np.array(centers)
    for _ in range(10):
        lab = ((X[:, None, :] - C[None]) ** 2).sum(-1).argmin(1)
        C = np.array(
            [X[lab == k].mean(0) if np.any(lab == k) else C[k] for k in range(n_components)]
        )
    resp = np.eye(n_components)[lab]

    prev = -np.inf
    eye = np.eye(d)
    for _ in range(n_iter):
        # M step
        nk = resp.sum(0) + 10 * np.finfo(float).eps
        weights = nk / N
        means = (resp.T @ X) / nk[:, None]
        covars = np.empty((n_components, d, d))
        for k in range(n_components):
            Dw = np.sqrt(resp[:, k, None]) * (X - means[k])  # weighted residuals (N, d)
            covars[k] = np.ascontiguousarray(Dw.T) @ Dw / nk[k] + reg_covar * eye
        # E step
        prec_chol = _precision_cholesky(covars)
        lp = _log_gauss(X, means, prec_chol) + np.log(weights)
        m = lp.max(1, keepdims=True)
        lse = m[:, 0] + np.log(np.exp(lp - m).sum(1))
        resp = np.exp(lp - lse[:, None])
        ll = lse.mean()
        if abs(ll - prev) < tol:
            break
        prev = ll
    return {"means": means, "covars": covars, "weights": weights}


@functools.lru_cache(maxsize=4)
def _cached_prior(seed: int) -> dict[str, np.ndarray]:
    rng = np.random.default_rng(seed)
    prior = fit_pose_prior(sample_plausible_poses(2000, rng), n_components=8, seed=seed)
    for a in prior.values():
        a.setflags(write=False)
    return prior


def generate_pose_prior(seed: int = 0) -> dict[str, np.ndarray]:
    """An 8-component GMM fitted to :func:`sample_plausible_poses` (memoised, deterministic).

    Returns means (8, 69), covars (8, 69, 69), weights (8,), float64 (fresh copies).
    """
    return {k: v.copy() for k, v in _cached_prior(seed).items()}


class GMMPosePrior(torch.nn.Module):
    """-log sum_k w_k N(pose; mu_k, Sigma_k) for body poses (B, 69) -> (B,).

    Buffers (float64 until moved): means (K, 69), prec_chol (K, 69, 69) lower factors with
    L L^T = Sigma^-1, log_const (K,) = log w_k + 0.5 log det Sigma_k^-1 - 34.5 log 2 pi.
    The forward pass runs in the dtype of the pose; the constants were formed in float64.
    """

    def __init__(self, means, covars, weights):
        super().__init__()
        means = np.asarray(means, dtype=np.float64)
        covars = np.asarray(covars, dtype=np.float64)
        weights = np.asarray(weights, dtype=np.float64).reshape(-1)
        K = weights.shape[0]
        if (
            means.ndim != 2
            or means.shape[0] != K
            or covars.shape != (K, means.shape[1], means.shape[1])
        ):
            raise ValueError(
                f"GMMPosePrior: inconsistent shapes means {means.shape}, covars {covars.shape}, "
                f"weights {weights.shape}; expected (K, d), (K, d, d), (K,)"
            )
        if np.any(weights <= 0):
            raise ValueError(f"GMMPosePrior: weights must be positive, got {weights}")
        weights = weights / weights.sum()
        d = means.shape[1]
        try:
            prec_chol = _precision_cholesky(covars)
        except np.linalg.LinAlgError as e:
            raise ValueError("GMMPosePrior: a covariance is not positive definite") from e
        half_logdet_prec = np.log(np.diagonal(prec_chol, axis1=1, axis2=2)).sum(1)
        log_const = np.log(weights) + half_logdet_prec - 0.5 * d * np.log(2 * np.pi)
        self.register_buffer("means", torch.tensor(means))
        self.register_buffer("prec_chol", torch.tensor(prec_chol))
        self.register_buffer("log_const", torch.tensor(log_const))

    def forward(self, body_pose: Tensor) -> Tensor:
        """body_pose (B, 69) axis-angle radians -> (B,) negative log-likelihood (nats)."""
        if body_pose.ndim != 2 or body_pose.shape[1] != self.means.shape[1]:
            raise ValueError(
                f"GMMPosePrior: expected (B, {self.means.shape[1]}), got {tuple(body_pose.shape)}"
            )
        x = body_pose
        diff = x[:, None, :] - self.means.to(x)[None]  # (B, K, d)
        y = torch.einsum("bkd,kde->bke", diff, self.prec_chol.to(x))
        logp = self.log_const.to(x)[None] - 0.5 * (y * y).sum(-1)
        return -torch.logsumexp(logp, dim=1)
