"""Anomaly score functions s(e_t; D_e) over the nominal embedding cache (paper Sec. IV-A).

Convention everywhere: a HIGHER score means MORE anomalous, and an observation
is an anomaly iff ``score > tau`` (strict; paper's ``eq:anomaly-classifier``).

Two families from the score-function ablation (appendix ``supp:score-fn-analysis``):

* top-k: ``s(e_t; D_e) = -mean of the k largest cosine similarities`` between
  e_t and the cache (k=1 is the ``-max`` formula in Sec. IV-A). Unitless, in
  [-1, 1]. The similarities come from a nearest-neighbour search (FAISS inner
  product on unit vectors), so this module only reduces them.
* Mahalanobis: the distance of e_t from a Gaussian fitted to D_e, with the
  covariance shrunk towards a scaled identity so it is invertible when the
  cache is smaller than the embedding dimension. Unitless (standard deviations).

Calibrating tau with eq. (2) (``eq:emp-quantile``) needs the score of every
cache member *leave-one-out*, s(e_i; D_e \\ {e_i}), since otherwise a member
always finds itself (top-1 score -1). ``loo_topk_scores`` and
``MahalanobisModel.loo_scores`` provide those.

Pure numpy, no I/O; float64 internally.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

__all__ = [
    "MahalanobisModel",
    "ScoringError",
    "loo_topk_scores",
    "topk_score",
]

# Similarities are rounded to this many decimals before they are scored: the same text
# embedded in two batches can differ in the seventh decimal (1.0 to its copies in one
# batch, 1.0000002 to a copy embedded alone), and a nominal observation seen again must
# tie with its calibration scores, not land a hair beyond every one of them.
DECIMALS = 4
# Cosine similarities from float32 embeddings can overshoot +-1 by rounding;
# anything further out is not a cosine similarity (e.g. FAISS's -FLT_MAX padding
# for missing results, or L2 distances passed by mistake).
_COSINE_SLACK = 1e-3
# FAISS marks "fewer results than asked" with this label.
_FAISS_MISSING = -1
# Leave-one-out denominators 1 - c q at or below this mean the covariance
# without the point is singular (possible only with shrinkage 0): distance +inf.
_SINGULAR_DENOM = 1e-10


class ScoringError(ValueError):
    """A score function got an input it cannot score; ``field`` names the input."""

    def __init__(self, message: str, *, field: str) -> None:
        super().__init__(message)
        self.field = field


# ---------------------------------------------------------------- top-k


def _check_k(k: int, m: int, *, extra: int = 0) -> None:
    """1 <= k and k + extra <= m (m: neighbours per row; extra=1 for leave-one-out)."""
    if isinstance(k, bool) or not isinstance(k, int | np.integer):
        raise ScoringError(f"k must be an int, got {type(k).__name__}", field="k")
    if k < 1:
        raise ScoringError(f"k must be >= 1, got {k}", field="k")
    if k + extra > m:
        need = "k" if extra == 0 else f"k+{extra}"
        raise ScoringError(
            f"k={k} needs at least {need}={k + extra} neighbours per row, got {m}", field="k"
        )


def _as_similarities(similarities: np.ndarray) -> np.ndarray:
    """(n, m) cosine similarities, each row non-increasing, as float64."""
    sims = np.asarray(similarities, dtype=np.float64)
    if sims.ndim != 2:
        raise ScoringError(
            f"similarities must be 2-D (n, m), got shape {sims.shape}", field="similarities"
        )
    if not np.all(np.isfinite(sims)) or np.any(np.abs(sims) > 1.0 + _COSINE_SLACK):
        raise ScoringError(
            "similarities must be finite cosine similarities in [-1, 1] "
            "(missing search results? L2 distances?)",
            field="similarities",
        )
    if sims.shape[1] > 1 and np.any(np.diff(sims, axis=1) > 0):
        raise ScoringError(
            "each row of similarities must be sorted descending, as a search returns it",
            field="similarities",
        )
    return sims


def topk_score(similarities: np.ndarray, k: int) -> np.ndarray:
    """Top-k score: minus the mean of each row's k largest cosine similarities.

    s(e_t; D_e) = -(1/k) sum_{j<=k} cos(e_t, e_(j)), with e_(j) the j-th most
    similar cache member; k=1 is the ``-max`` score of Sec. IV-A. Each similarity is
    rounded to :data:`DECIMALS` places first (float noise must not order equal texts).

    Args:
        similarities: (n, m) cosine similarities of n queries to their m >= k
            nearest cache members, each row sorted descending (as FAISS returns
            them). Unitless, in [-1, 1].
        k: number of neighbours to average, 1 <= k <= m.

    Returns:
        (n,) float64 scores in [-1, 1]; higher = more anomalous.

    Raises:
        ScoringError: ``field="k"`` for k < 1 or k > m; ``field="similarities"``
            for a non-2-D, non-finite, out-of-range or unsorted array.
    """
    sims = _as_similarities(similarities)
    _check_k(k, sims.shape[1])
    scores: np.ndarray = -np.round(sims[:, :k], DECIMALS).mean(axis=1)
    return scores


def loo_topk_scores(
    similarities: np.ndarray,
    labels: np.ndarray,
    self_labels: np.ndarray,
    k: int,
) -> np.ndarray:
    """Leave-one-out top-k scores s(e_i; D_e \\ {e_i}) of cache members, for eq. (2).

    Search each member against the cache it belongs to with k+1 neighbours, then
    per row drop the member's own entry (the one whose label equals its own id)
    and score the first k of the rest. Own entry is found by label, not by
    position: with an exact duplicate in the cache another id ties with it and
    may come first. If the own id is absent (more than k ties pushed it out of
    the k+1 results) the last column is dropped instead, which leaves the same
    top k. Only the member itself is left out; duplicates under other ids stay
    (they are genuine other experiences). If the own id occurs more than once
    in a row, only its first occurrence is dropped.

    Args:
        similarities: (n, m) cosine similarities, m >= k+1, each row sorted
            descending (FAISS ``D``).
        labels: (n, m) integer cache ids of those neighbours (FAISS ``I``).
        self_labels: (n,) integer cache id of each queried member.
        k: number of neighbours in the score, 1 <= k <= m-1.

    Returns:
        (n,) float64 leave-one-out top-k scores; higher = more anomalous.

    Raises:
        ScoringError: ``field="k"`` if k < 1 or k+1 > m; ``field="labels"`` for a
            shape mismatch, a non-integer dtype or a padding label -1 (the search
            returned fewer than k+1 results: the cache is too small);
            ``field="self_labels"`` for a bad ``self_labels``;
            ``field="similarities"`` as in :func:`topk_score`.
    """
    sims = _as_similarities(similarities)
    n, m = sims.shape
    _check_k(k, m, extra=1)
    ids = np.asarray(labels)
    if ids.shape != sims.shape or not np.issubdtype(ids.dtype, np.integer):
        raise ScoringError(
            f"labels must be integer ids of shape {sims.shape}, got {ids.dtype} {ids.shape}",
            field="labels",
        )
    if np.any(ids == _FAISS_MISSING):
        raise ScoringError(
            f"labels contain {_FAISS_MISSING} (fewer than {m} results): the cache needs "
            f"at least k+1={k + 1} members",
            field="labels",
        )
    own = np.asarray(self_labels)
    if own.shape != (n,) or not np.issubdtype(own.dtype, np.integer):
        raise ScoringError(
            f"self_labels must be integer ids of shape ({n},), got {own.dtype} {own.shape}",
            field="self_labels",
        )
    is_own = ids == own[:, None]
    drop = np.where(is_own.any(axis=1), is_own.argmax(axis=1), m - 1)
    keep = np.ones((n, m), dtype=bool)
    keep[np.arange(n), drop] = False
    return topk_score(sims[keep].reshape(n, m - 1), k)


# ---------------------------------------------------------------- Mahalanobis


def _as_vectors(vectors: np.ndarray, d: int | None = None) -> np.ndarray:
    """(n, d) finite float64 matrix."""
    x = np.asarray(vectors, dtype=np.float64)
    if x.ndim != 2 or (d is not None and x.shape[1] != d):
        want = "(n, d)" if d is None else f"(n, {d})"
        raise ScoringError(f"vectors must have shape {want}, got {x.shape}", field="vectors")
    if not np.all(np.isfinite(x)):
        raise ScoringError("vectors must be finite", field="vectors")
    return x


def _spd_eigh(matrix: np.ndarray, what: str) -> tuple[np.ndarray, np.ndarray]:
    """Eigen-decomposition (w (d,), V (d, d)) of a symmetric positive definite matrix.

    Raises ScoringError(field="covariance") if it is not numerically positive
    definite (smallest eigenvalue <= d * eps * largest).
    """
    w, v = np.linalg.eigh(matrix)
    d = matrix.shape[0]
    if not w[-1] > 0 or w[0] <= w[-1] * d * np.finfo(np.float64).eps:
        raise ScoringError(
            f"{what} is singular (eigenvalues {w[0]:.3g}..{w[-1]:.3g}); "
            "use shrinkage > 0 or more, non-identical vectors",
            field="covariance",
        )
    return w, v


@dataclass(frozen=True, eq=False)
class MahalanobisModel:
    """Mahalanobis score against a Gaussian fit of the cache, with covariance shrinkage.

    Fitted from the cache D_e = {x_i} (n, d):

    * mean mu = (1/n) sum x_i, scatter M = sum (x_i - mu)(x_i - mu)^T,
    * sample covariance S = M / (n-1),
    * shrunk covariance Sigma = (1 - lambda) S + lambda nu I with nu = trace(S) / d
      (the mean variance, so the target keeps the total variance),
    * score s(x) = sqrt((x - mu)^T Sigma^{-1} (x - mu)), unitless, >= 0.

    Attributes:
        mean: (d,) mu.
        precision: (d, d) Sigma^{-1}, symmetric positive definite.
        sample_covariance: (d, d) S, unshrunk (kept for the closed-form
            leave-one-out scores).
        shrinkage: lambda in [0, 1].
        nu: shrinkage target scale (variance per dimension, squared embedding units).
        n: number of fitted vectors, >= 3.

    Arrays are read-only; ``eq=False`` since numpy arrays have no scalar ``==``.
    """

    mean: np.ndarray
    precision: np.ndarray
    sample_covariance: np.ndarray
    shrinkage: float
    nu: float
    n: int

    @classmethod
    def fit(
        cls,
        vectors: np.ndarray,
        shrinkage: float = 0.1,
        *,
        nu: float | None = None,
    ) -> MahalanobisModel:
        """Fit mu and the shrunk covariance to the cache.

        Args:
            vectors: (n, d) cache embeddings, n >= 3.
            shrinkage: lambda in [0, 1]; 0 is the plain sample covariance (needs
                n > d), 1 is the isotropic nu I.
            nu: override the target scale trace(S)/d, e.g. to keep the full-cache
                nu when refitting without one point (see :meth:`loo_scores`).

        Raises:
            ScoringError: ``field="size"`` for n < 3; ``field="shrinkage"`` or
                ``field="nu"`` out of range; ``field="vectors"`` for a bad array;
                ``field="covariance"`` if Sigma is singular.
        """
        x = _as_vectors(vectors)
        n, d = x.shape
        if n < 3:
            raise ScoringError(f"need at least 3 vectors, got {n}", field="size")
        lam = float(shrinkage)
        if not 0.0 <= lam <= 1.0:
            raise ScoringError(f"shrinkage must be in [0, 1], got {shrinkage}", field="shrinkage")
        mu = x.mean(axis=0)
        z = x - mu
        s = (z.T @ z) / (n - 1)
        scale = float(np.trace(s)) / d if nu is None else float(nu)
        if not (np.isfinite(scale) and scale >= 0.0):
            raise ScoringError(f"nu must be finite and >= 0, got {nu}", field="nu")
        sigma = (1.0 - lam) * s + lam * scale * np.eye(d)
        w, v = _spd_eigh(sigma, "the shrunk covariance")
        precision = (v / w) @ v.T
        precision = 0.5 * (precision + precision.T)
        for arr in (mu, precision, s):
            arr.setflags(write=False)
        return cls(mean=mu, precision=precision, sample_covariance=s, shrinkage=lam, nu=scale, n=n)

    @property
    def dim(self) -> int:
        """Embedding dimension d."""
        return int(self.mean.shape[0])

    def score(self, vectors: np.ndarray) -> np.ndarray:
        """Mahalanobis distances sqrt((x - mu)^T Sigma^{-1} (x - mu)).

        Args:
            vectors: (m, d) embeddings to score.

        Returns:
            (m,) float64 distances >= 0; higher = more anomalous.
        """
        z = _as_vectors(vectors, self.dim) - self.mean
        d2 = np.einsum("ij,ij->i", z @ self.precision, z)
        distances: np.ndarray = np.sqrt(np.maximum(d2, 0.0))
        return distances

    def loo_scores(self, vectors: np.ndarray) -> np.ndarray:
        """Leave-one-out distances d_i = s(x_i; D \\ {x_i}) of the fitted vectors, closed form.

        Each x_i is scored by the model refitted without it, with the SAME
        shrinkage and the SAME nu (the full-cache trace(S)/d; refitting nu per
        point would change the target by O(1/n) and break the rank-one update).
        With u = x_i - mu:

            mu_{-i}    = mu - u / (n-1)
            M_{-i}     = M - n/(n-1) u u^T
            Sigma_{-i} = (1-lambda) M_{-i}/(n-2) + lambda nu I = A - c u u^T,
                A = (1-lambda) M/(n-2) + lambda nu I,  c = (1-lambda) n / ((n-1)(n-2))
            x_i - mu_{-i} = n/(n-1) u

        and Sherman-Morrison with q = u^T A^{-1} u gives

            d_i^2 = (n/(n-1))^2 q / (1 - c q).

        A is decomposed once (eigh), so the cost is O(d^3 + n d^2) instead of n
        refits. If 1 - c q <= 1e-10 the covariance without x_i is singular (only
        possible with shrinkage 0) and x_i lies off its support: d_i = +inf.

        Args:
            vectors: (n, d) exactly the vectors passed to :meth:`fit`, same order.

        Returns:
            (n,) float64 leave-one-out distances >= 0 (possibly +inf, see above).

        Raises:
            ScoringError: ``field="vectors"`` if the shape or mean shows these are
                not the fitted vectors.
        """
        x = _as_vectors(vectors, self.dim)
        n, lam = self.n, self.shrinkage
        if x.shape[0] != n:
            raise ScoringError(
                f"loo_scores needs the {n} fitted vectors, got {x.shape[0]}", field="vectors"
            )
        tol = 1e-8 * (1.0 + float(np.max(np.abs(x))))
        if not np.allclose(x.mean(axis=0), self.mean, rtol=0.0, atol=tol):
            raise ScoringError(
                "loo_scores needs the vectors the model was fitted on", field="vectors"
            )
        u = x - self.mean
        scatter = self.sample_covariance * (n - 1)
        a = (1.0 - lam) * scatter / (n - 2) + lam * self.nu * np.eye(self.dim)
        w, v = _spd_eigh(a, "the leave-one-out base matrix A")
        y = u @ v
        q = np.einsum("ij,ij->i", y / w, y)
        c = (1.0 - lam) * n / ((n - 1) * (n - 2))
        denom = 1.0 - c * q
        ratio = (n / (n - 1)) ** 2
        safe = denom > _SINGULAR_DENOM
        d2 = np.where(safe, ratio * q / np.where(safe, denom, 1.0), np.inf)
        return np.sqrt(np.maximum(d2, 0.0))
