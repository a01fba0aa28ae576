"""Joint fits for many sensor pairs at once, read from one Gram accumulator (design.md §2–§3).

Each pair (i, j) is the paper's least-squares problem (eq. 15) for the point fixed in both frames: c in i's
frame, l in j's. All pairs are solved together: one batched 6×6 eigendecomposition, no loop over pairs.
"""

from __future__ import annotations

from dataclasses import dataclass, fields
from functools import lru_cache

import numpy as np

# Eigenvalues of A/n at or below this are zero to rounding (A/n has eigenvalues in [0, 2]; the Gram's own
# rounding leaves ~1e-15 where the data hold nothing). Its square root, 1e-5, is the matching cut-off on the
# normalised singular values of the stacked system, used by the reference SVD solve.
NUMERIC_FLOOR = 1e-10

# Hinge test (see `pair_fits`): an axis counts as exercised when A/n's eigenvalue exceeds HINGE_MARGIN times
# the rotation variance the residual noise alone could produce (at most ~1.5× σ²/L², derived below).
HINGE_MARGIN = 4.0

# Rounding budget of SSE/n read from the Gram, in units of Σ(‖t_i‖² + ‖t_j‖²)/(n μ_min): 64 × machine epsilon.
ROUNDING = 64 * np.finfo(float).eps
_TINY = np.finfo(float).tiny


@dataclass(frozen=True)
class PairFits:
    """Fits for p pairs (i, j): arrays over pairs, SI units. c is in sensor i's frame, l in sensor j's."""

    pairs: np.ndarray  # (p, 2) int
    c: np.ndarray  # (p, 3) m
    l: np.ndarray  # (p, 3) m
    rms: np.ndarray  # (p,) m, sqrt(Σ‖e_k‖²/n)
    epsilon: np.ndarray  # (p,) m, the paper's ε = sqrt(Σ‖e_k‖²)/n (eq. 19)
    singular_values: np.ndarray  # (p, 6) of the stacked 3n×6 system, ÷√n, descending
    hinge: np.ndarray  # (p,) bool: exactly one direction left unexercised
    axis_i: np.ndarray  # (p, 3) hinge axis in i's frame (NaN when not a hinge)
    axis_j: np.ndarray  # (p, 3) the same axis in j's frame
    coverage: np.ndarray  # (p, 3) 1 − σ_k(M), ascending: coverage[:, 0] is the least exercised axis
    c_stderr: np.ndarray  # (p,) m, sqrt(trace Cov(c))
    l_stderr: np.ndarray  # (p,) m
    c_cov: np.ndarray  # (p, 3, 3) m²
    l_cov: np.ndarray  # (p, 3, 3) m²
    n: np.ndarray  # (p,) frames used (both sensors valid)
    rank: np.ndarray  # (p,) directions solved: 6 ball, 5 hinge, 3 no relative rotation, 0 no data
    noise_floor: np.ndarray  # (p,) σ²/L², the rotation variance the residual noise alone would explain
    separation: np.ndarray  # (p,) m, rms distance between the two sensors (2L)
    rms_floor: np.ndarray  # (p,) m, rounding level of rms read from the Gram: smaller values mean 0

    def __len__(self) -> int:
        return len(self.pairs)

    def take(self, index, swap=None) -> "PairFits":
        """Rows `index`; where `swap` is True the pair is reversed to (j, i) (c↔l, axis_i↔axis_j)."""
        idx = np.asarray(index, dtype=np.intp).reshape(-1)
        out = {name: getattr(self, name)[idx] for name in _FIELDS}
        sw = None if swap is None else np.asarray(swap, dtype=bool).reshape(-1)
        if sw is not None and sw.any():
            for a, b in (("c", "l"), ("axis_i", "axis_j"), ("c_stderr", "l_stderr"), ("c_cov", "l_cov")):
                x, y = out[a], out[b]
                s = sw.reshape((-1,) + (1,) * (x.ndim - 1))
                out[a], out[b] = np.where(s, y, x), np.where(s, x, y)
            out["pairs"] = np.where(sw[:, None], out["pairs"][:, ::-1], out["pairs"])
        return PairFits(**out)

    def square(self, name: str, n_sensors: int, fill=np.nan) -> np.ndarray:
        """A per-pair scalar (e.g. "rms") as a symmetric (m, m) matrix, `fill` where no pair was fitted."""
        out = np.full((n_sensors, n_sensors), fill, dtype=float)
        v = np.asarray(getattr(self, name), dtype=float)
        out[self.pairs[:, 0], self.pairs[:, 1]] = v
        out[self.pairs[:, 1], self.pairs[:, 0]] = v
        return out


_FIELDS = tuple(f.name for f in fields(PairFits))


def all_pairs(n_sensors: int) -> np.ndarray:
    """Every pair (i, j) with i < j, in row-major order: (m(m−1)/2, 2)."""
    return _all_pairs(int(n_sensors)).copy()


@lru_cache(maxsize=8)
def _all_pairs(m: int) -> np.ndarray:
    # triu_indices costs more than a whole refit step on 16 sensors; the live service asks ~30×/s.
    i, j = np.triu_indices(m, k=1)
    P = np.stack([i, j], axis=1)
    P.setflags(write=False)
    return P


def pair_fits(acc, pairs=None, hinge_margin: float = HINGE_MARGIN) -> PairFits:
    """Fit the joint of every pair in `pairs` ((p, 2) indices; default all pairs) from accumulator `acc`.

    Solve. A/n = V diag(μ) Vᵀ (μ ascending); u = Σ_kept v_k (v_kᵀ b/n) / μ_k — the pseudo-inverse restricted
    to the kept directions, i.e. the minimum-norm solution, the paper's point "closest to the sensor origins".
    Dropped directions get no component, so a near-singular direction can never push the centre away.

    Which directions are kept. A/n's eigenvalues are 1 ± σ_k(M) (design.md §3), so only the three smallest,
    μ_k = 1 − σ_k(M) — how far the joint turned about each principal axis — can be missing:
      * μ_k ≤ NUMERIC_FLOOR: nothing there at all (rounding level);
      * μ_k < hinge_margin · σ²/L²: no more than the residual noise alone explains. σ² is the residual
        variance per coordinate of the fit with every numerically present direction kept (SSE/(3n − r)),
        L the lever: half the rms sensor separation, L² = Σ‖t_j − t_i‖²/(4n), which never exceeds the rms of
        |c|, |l|. Rotation jitter of variance s² per axis on each sensor gives μ ≈ 2s² about an unexercised
        axis, and a residual variance of at least (2/3)s²(|c|²+|l|²) ≥ (4/3)s²L², so noise alone makes
        μ/(σ²/L²) ≤ 1.5; HINGE_MARGIN = 4 leaves room. An axis turned through a few degrees rms at 10 cm
        levers and tracker-level noise (0.5 mm) gives a ratio of tens to hundreds: it stays 3-D.
    One direction dropped is a hinge; its eigenvector (a_i, a_j) is the axis in both frames.

    Standard errors. Cov(u) = σ̂² A⁺_kept with σ̂² = SSE/(3n − r) and A⁺_kept = Σ_kept v_k v_kᵀ / λ_k;
    c_stderr = sqrt(trace Cov(c)). Directions pinned by the min-norm rule carry no variance (a rule, not a
    measurement): for a hinge, c_stderr is the uncertainty of the point picked on the axis.
    """
    m = acc.n_sensors
    P = all_pairs(m) if pairs is None else np.asarray(pairs, dtype=np.intp).reshape(-1, 2)
    A, b, dd, n = acc.normal_equations(P)
    p = len(P)
    has = n > 0
    nn = np.where(has, n, 1.0)
    An = A / nn[:, None, None]
    bn = b / nn[:, None]
    ddn = dd / nn
    mu, V = np.linalg.eigh(An)  # ascending; (p, 6), (p, 6, 6) with V[:, :, k] the k-th eigenvector
    coef = np.einsum("pik,pi->pk", V, bn)  # v_kᵀ b / n
    floor_ok = mu > NUMERIC_FLOOR
    safe_mu = np.where(floor_ok, mu, 1.0)
    gain = np.where(floor_ok, coef**2 / safe_mu, 0.0)  # SSE/n removed by each direction

    # Residual variance with every numerically present direction kept, and the lever.
    r_num = floor_ok.sum(axis=1)
    sse_num = np.maximum(ddn - gain.sum(axis=1), 0.0) * nn
    dof_num = np.maximum(3.0 * nn - r_num, 1.0)
    lever2 = np.maximum(ddn / 4.0, _TINY)
    noise_floor = (sse_num / dof_num) / lever2

    keep = floor_ok.copy()
    keep[:, :3] &= mu[:, :3] >= hinge_margin * noise_floor[:, None]
    keep &= has[:, None]
    rank = keep.sum(axis=1)

    w = np.where(keep, coef / safe_mu, 0.0)
    u = np.einsum("pik,pk->pi", V, w)
    sse = np.maximum(ddn - np.where(keep, gain, 0.0).sum(axis=1), 0.0) * nn
    rms = np.sqrt(sse / nn)
    eps = np.sqrt(sse) / nn
    sigma2 = sse / np.maximum(3.0 * nn - rank, 1.0)
    inv = np.where(keep, 1.0 / safe_mu, 0.0)
    cov = ((V * inv[:, None, :]) @ V.transpose(0, 2, 1)) * (sigma2 / nn)[:, None, None]  # V diag(inv) Vᵀ σ²/n
    c_cov, l_cov = cov[:, :3, :3], cov[:, 3:, 3:]

    # SSE = Σ‖d‖² − Σ (v_kᵀb)²/λ_k loses about ε·Σ‖t‖²/μ_min to rounding (μ_min: smallest kept eigenvalue).
    mu_kept = np.where(keep, mu, np.inf).min(axis=1)
    mu_kept = np.where(np.isfinite(mu_kept), np.minimum(mu_kept, 1.0), 1.0)

    hinge = rank == 5
    axis = V[:, :, 0].reshape(p, 2, 3)  # the dropped direction of a hinge is the smallest eigenvalue's: (a_i, a_j)
    with np.errstate(invalid="ignore", divide="ignore"):
        axis = axis / np.sqrt((axis * axis).sum(axis=2, keepdims=True))
    # An eigenvector's sign is arbitrary: make a_i's largest component positive (a_j follows, same world axis).
    sign = np.sign(axis[np.arange(p), 0, np.abs(axis[:, 0]).argmax(axis=1)])
    sign = np.where(sign == 0, 1.0, sign)
    axis = np.where(hinge[:, None, None], axis * sign[:, None, None], np.nan)
    ai, aj = axis[:, 0], axis[:, 1]

    sv = np.sqrt(np.maximum(mu, 0.0))[:, ::-1]
    coverage = np.minimum(np.maximum(mu[:, :3], 0.0), 1.0)
    nan3 = np.where(has[:, None], 0.0, np.nan)
    nan1 = np.where(has, 0.0, np.nan)
    return PairFits(
        pairs=P,
        c=u[:, :3] + nan3,
        l=u[:, 3:] + nan3,
        rms=rms + nan1,
        epsilon=eps + nan1,
        singular_values=sv + np.where(has[:, None], 0.0, np.nan),
        hinge=hinge & has,
        axis_i=ai,
        axis_j=aj,
        coverage=coverage + nan3,
        c_stderr=np.sqrt(np.trace(c_cov, axis1=1, axis2=2)) + nan1,
        l_stderr=np.sqrt(np.trace(l_cov, axis1=1, axis2=2)) + nan1,
        c_cov=c_cov + nan1[:, None, None],
        l_cov=l_cov + nan1[:, None, None],
        n=n,
        rank=np.where(has, rank, 0),
        noise_floor=noise_floor + nan1,
        separation=np.sqrt(np.maximum(ddn, 0.0)) + nan1,
        rms_floor=np.sqrt(ROUNDING * (np.maximum(ddn, 0.0) + acc.translation_power(P)) / mu_kept) + nan1,
    )
