"""Joint fits for many sensor pairs at once, read from one Gram accumulator (docs/design.md §2–§3).

Each pair (i, j) is the paper's least-squares problem (eq. 15) for the point fixed in both frames: c in i's
frame, l in j's. All pairs are solved together: one batched 6×6 eigendecomposition, no loop over pairs.
"""

from __future__ import annotations

from dataclasses import dataclass, fields
from typing import NamedTuple

import numpy as np

from flockcal.solver.gram_layout import all_pairs_of

# Eigenvalues of A/n at or below this are zero to rounding (A/n has eigenvalues in [0, 2]; the Gram's own
# rounding leaves ~1e-15 where the data hold nothing).
NUMERIC_FLOOR = 1e-10

# How closely the data must pin the joint centre along a direction for it to count (docs/design.md §3a): the
# standard error there, with the bias rotation noise leaves in least squares, at most this. Option of
# `flockcal fit` and `serve` (`--tolerance-mm`).
TOLERANCE_M = 0.005

# A direction carries rotation beyond noise when μ_k is at least this multiple of what the two sensors'
# measured rotation jitter alone adds to it (≈ s_i² + s_j²). Below that the least-squares value along it is
# noise fitting noise, so the estimate keeps the minimum-norm point there, as the paper does for a hinge.
ROTATION_MARGIN = 4.0

# Batch-means standard errors come from few blocks early in a take: they are read at this one-sided upper
# confidence level, so a joint is called pinned only when the data say so with some confidence.
SE_CONFIDENCE = 0.8
_Z_SE = 0.8416  # the standard normal quantile of SE_CONFIDENCE

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
    hinge: np.ndarray  # (p,) bool: a determined hinge — exactly one free direction, its axis pinned
    determined: np.ndarray  # (p,) bool: a ball with every direction pinned, or a hinge (docs/design.md §3a)
    axis_i: np.ndarray  # (p, 3) hinge axis in i's frame (NaN when not a hinge)
    axis_j: np.ndarray  # (p, 3) the same axis in j's frame
    coverage: np.ndarray  # (p, 3) 1 − σ_k(M), ascending: coverage[:, 0] is the least exercised axis
    c_stderr: np.ndarray  # (p,) m, sqrt(trace Cov(c))
    l_stderr: np.ndarray  # (p,) m
    c_cov: np.ndarray  # (p, 3, 3) m²
    l_cov: np.ndarray  # (p, 3, 3) m²
    n: np.ndarray  # (p,) frames used (both sensors valid)
    rank: np.ndarray  # (p,) directions with rotation beyond noise (solved; the rest take the min-norm point)
    direction_error: np.ndarray  # (p, 3) m: the centre's error along the three least-turned directions (inf: none)
    rotation_noise: np.ndarray  # (p,) what the two sensors' rotation jitter adds to μ_k (rad²)
    separation: np.ndarray  # (p,) m, rms distance between the two sensors (2L)
    rms_floor: np.ndarray  # (p,) m, rounding level of rms read from the Gram: smaller values mean 0
    # (p,) m: a hinge's least-squares point on its axis, as a slide from c along axis_i (and from l along
    # axis_j); its error is direction_error[:, 0]. NaN: not a hinge, or no rotation about the axis beyond noise.
    axis_offset: np.ndarray
    # (p, 3) m: the classical (white-noise) standard error along the three least-turned directions, the part
    # of direction_error that more frames of any motion shrink as 1/√n (inf where nothing turned). Where it is
    # far below direction_error, correlated residuals (soft tissue) set the error, not the frame count.
    noise_error: np.ndarray

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


def unfitted(pairs) -> PairFits:
    """PairFits for `pairs` with nothing measured: NaN numbers, no hinge, nothing determined, no frames.
    Stands in where only the joint points are known (a fit read from a file, a saved skeleton's start)."""
    P = np.asarray(pairs, dtype=int).reshape(-1, 2)
    p = len(P)

    def nan(*shape):
        return np.full((p, *shape), np.nan)

    no = np.zeros(p, dtype=bool)
    zero = np.zeros(p, dtype=int)
    return PairFits(P, nan(3), nan(3), nan(), nan(), nan(6), no, no, nan(3), nan(3), nan(3), nan(), nan(),
                    nan(3, 3), nan(3, 3), zero, zero.copy(), nan(3), nan(), nan(), nan(), nan(), nan(3))


def all_pairs(n_sensors: int) -> np.ndarray:
    """Every pair (i, j) with i < j, in row-major order: (m(m−1)/2, 2)."""
    return all_pairs_of(int(n_sensors)).copy()


class JointEstimates(NamedTuple):
    """The joint centres alone, (p, 3) each in the two sensors' frames: `PairFits.c` and `.l`, bit for bit."""

    c: np.ndarray
    l: np.ndarray  # noqa: E741 (the paper's name)


def joint_estimates(acc, pairs, tolerance: float = TOLERANCE_M) -> JointEstimates:
    """`pair_fits(acc, pairs, tolerance)`'s c and l, without the error bars, axes and floors that only a
    full fit reports: the slip loop refits its joints after every 1/30 s micro-batch and reads no more,
    and those parts were about a third of its refits' numpy calls."""
    return _pair_fits(acc, pairs, tolerance, estimates_only=True)


def pair_fits(acc, pairs=None, tolerance: float = TOLERANCE_M) -> PairFits:
    """Fit the joint of every pair in `pairs` ((p, 2) indices; default all pairs) from accumulator `acc`,
    and decide from the data's own noise whether each joint is determined (docs/design.md §3a).

    Solve. A/n = V diag(μ) Vᵀ (μ ascending); u = Σ_kept v_k (v_kᵀ b/n) / μ_k — the pseudo-inverse over the
    kept directions, i.e. the minimum-norm solution, the paper's point "closest to the sensor origins".
    Only the three smallest, μ_k = 1 − σ_k(M), can be missing (docs/design.md §3). A direction is kept when μ_k is
    above rounding and at least ROTATION_MARGIN × the rotation noise μ₀ = s_i² + s_j², measured per sensor
    from the take (`acc.rotation_noise()`), apart from position noise. Kept directions are plain least squares.

    Decide. Along each kept direction the centre's standard error is the larger of the classical
    σ̂/√(n μ_k) and the batch-means one from the accumulator's score blocks (which holds when residuals are
    correlated in time, as soft tissue makes them), read at SE_CONFIDENCE for the blocks it comes from; the
    bias rotation noise leaves in least squares, |v_kᵀu| μ₀/μ_k, adds to it. A direction is pinned when that
    error is within `tolerance`. Ball: all three pinned. Hinge: only the least-turned one free, and its axis
    pinned — the axis tilts by about (μ₀ + √(μ₁μ₂'/n_eff))/(μ₂' − μ₁) rad, which must not move the centre by
    more than `tolerance` at the sensors' lever. Anything else is undetermined: it keeps its numbers for
    inspection but is not a joint anybody should draw.

    Standard errors. Cov(u) = Σ_kept v_k v_kᵀ se_k² (se_k the larger estimate, without the confidence
    scaling the decision applies); c_stderr = sqrt(trace Cov(c)), infinite for an
    undetermined joint with a direction the data did not turn about (the point there is a rule, not a
    measurement); for a hinge the axis direction is left out (its point on the axis is the paper's rule).
    """
    return _pair_fits(acc, pairs, tolerance, estimates_only=False)


def _pair_fits(acc, pairs, tolerance: float, estimates_only: bool):
    """`pair_fits`, or only its c and l (`joint_estimates`)."""
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

    noise = acc.rotation_noise()
    mu0 = noise[P[:, 0]] + noise[P[:, 1]]
    mu0 = np.where(np.isfinite(mu0), mu0, np.inf)  # no jitter estimate yet: nothing counts as turned
    keep = floor_ok.copy()
    keep[:, :3] &= mu[:, :3] >= ROTATION_MARGIN * mu0[:, None]
    keep &= has[:, None]
    rank = keep.sum(axis=1)

    w = np.where(keep, coef / safe_mu, 0.0)
    u = np.einsum("pik,pk->pi", V, w)
    gain = np.where(keep, coef**2 / safe_mu, 0.0)  # SSE/n removed by each kept direction
    sse = np.maximum(ddn - gain.sum(axis=1), 0.0) * nn
    rms = np.sqrt(sse / nn)
    eps = np.sqrt(sse) / nn
    sigma2 = sse / np.maximum(3.0 * nn - rank, 1.0)

    # Classical and batch-means variance of u along each eigenvector.
    var_cl = sigma2[:, None] / (nn[:, None] * safe_mu)
    var_bm, blocks = _batch_means_variance(acc, P, u, V, nn, safe_mu)
    ok_bm = np.isfinite(var_bm)
    factor = _upper_chi2_factor(np.maximum(blocks - 1.0, 1.0))
    keep_cl = keep.copy()  # (a hinge's axis direction is dropped from `keep` below; its noise error stays)
    var = np.maximum(var_cl, np.where(ok_bm, var_bm, 0.0))  # the estimate, as reported
    var_hi = np.maximum(var_cl, np.where(ok_bm, var_bm * factor[:, None], 0.0))  # its upper bound, for deciding
    se = np.where(keep, np.sqrt(var_hi), np.inf)
    with np.errstate(invalid="ignore"):
        bias = np.abs(np.einsum("pik,pi->pk", V, u)) * np.where(np.isfinite(mu0), mu0, 0.0)[:, None] / safe_mu
    err = np.where(keep, np.hypot(se, np.where(np.isfinite(bias), bias, 0.0)), np.inf)[:, :3]
    pinned = err <= tolerance
    ball = pinned.all(axis=1)

    # Hinge: the least-turned direction free, the other two pinned, and the axis steady enough.
    one_free = ~pinned[:, 0] & pinned[:, 1] & pinned[:, 2]
    gap = np.maximum(mu[:, 1] - mu[:, 0], _TINY)
    # Frames that count as independent along the least-turned direction: the classical/batch-means ratio,
    # at least one per block (blocks are the batch-means' independent units), at most every frame.
    ratio = np.where(ok_bm[:, 0] & (var_bm[:, 0] > 0), var_cl[:, 0] / np.where(var_bm[:, 0] > 0, var_bm[:, 0], 1.0), 1.0)
    n_eff = np.clip(nn * ratio, np.maximum(blocks, 1.0), nn)
    tilt = (np.minimum(mu0, mu[:, 0]) + np.sqrt(np.maximum(mu[:, 0], 0.0) * mu[:, 1] / n_eff)) / gap
    lever = np.maximum(np.linalg.norm(u[:, :3], axis=1), np.linalg.norm(u[:, 3:], axis=1))
    hinge = one_free & (lever * tilt <= tolerance) & has
    determined = (ball | hinge) & has
    # A hinge's point along its axis is not pinned to the tolerance: the fit keeps the minimum-norm point
    # there and reports the least-squares value apart (a slide along the axis, with its error), and
    # solver/hinge_point.py places the point by the limb's bones, counting the data as far as they pin it.
    ls_along = np.where(hinge & keep[:, 0], coef[:, 0] / safe_mu[:, 0], np.nan)  # along v_0, in u's units
    if hinge.any():
        keep[:, 0] &= ~hinge
        rank = keep.sum(axis=1)
        w = np.where(keep, coef / safe_mu, 0.0)
        u = np.einsum("pik,pk->pi", V, w)
        gain = np.where(keep, coef**2 / safe_mu, 0.0)
        sse = np.maximum(ddn - gain.sum(axis=1), 0.0) * nn
        rms = np.sqrt(sse / nn)
        eps = np.sqrt(sse) / nn
    if estimates_only:  # c and l as below; the same arithmetic, so the same bits
        nan3 = np.where(has[:, None], 0.0, np.nan)
        return JointEstimates(u[:, :3] + nan3, u[:, 3:] + nan3)

    # Covariance over the kept directions (a hinge's free axis is the rule's, not the data's).
    inv = np.where(keep, var, 0.0)
    inv[:, 0] = np.where(hinge, 0.0, inv[:, 0])
    cov = (V * inv[:, None, :]) @ V.transpose(0, 2, 1)
    c_cov, l_cov = cov[:, :3, :3], cov[:, 3:, 3:]
    blind = ~determined & ~keep[:, :3].all(axis=1)  # a direction nothing turned about: no error bar exists
    c_se = np.where(blind, np.inf, np.sqrt(np.trace(c_cov, axis1=1, axis2=2)))
    l_se = np.where(blind, np.inf, np.sqrt(np.trace(l_cov, axis1=1, axis2=2)))

    # SSE = Σ‖d‖² − Σ (v_kᵀb)²/λ_k loses about ε·Σ‖t‖²/μ_min to rounding (μ_min: smallest kept eigenvalue).
    mu_kept = np.where(keep, mu, np.inf).min(axis=1)
    mu_kept = np.where(np.isfinite(mu_kept), np.minimum(mu_kept, 1.0), 1.0)

    axis = V[:, :, 0].reshape(p, 2, 3)  # a hinge's axis is the least-turned direction's: (a_i, a_j)
    with np.errstate(invalid="ignore", divide="ignore"):
        axis = axis / np.sqrt((axis * axis).sum(axis=2, keepdims=True))
    # An eigenvector's sign is arbitrary: make a_i's largest component positive (a_j follows, same world axis).
    sign = np.sign(axis[np.arange(p), 0, np.abs(axis[:, 0]).argmax(axis=1)])
    sign = np.where(sign == 0, 1.0, sign)
    axis = np.where(hinge[:, None, None], axis * sign[:, None, None], np.nan)
    ai, aj = axis[:, 0], axis[:, 1]
    # The least-squares point as a slide from c along a_i (v_0's child half is a_i times its length).
    axis_offset = ls_along * np.einsum("pi,pi->p", V[:, :3, 0], np.nan_to_num(ai))

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
        hinge=hinge,
        determined=determined,
        axis_i=ai,
        axis_j=aj,
        coverage=coverage + nan3,
        c_stderr=c_se + nan1,
        l_stderr=l_se + nan1,
        c_cov=c_cov + nan1[:, None, None],
        l_cov=l_cov + nan1[:, None, None],
        n=n,
        rank=np.where(has, rank, 0),
        direction_error=np.where(has[:, None], err, np.inf),
        rotation_noise=np.where(np.isfinite(mu0), mu0, np.nan) + nan1,
        separation=np.sqrt(np.maximum(ddn, 0.0)) + nan1,
        rms_floor=np.sqrt(ROUNDING * (np.maximum(ddn, 0.0) + acc.translation_power(P)) / mu_kept) + nan1,
        axis_offset=axis_offset,
        noise_error=np.where(has[:, None] & keep_cl[:, :3], np.sqrt(var_cl[:, :3]), np.inf),
    )


def _batch_means_variance(acc, P, u, V, n, mu) -> tuple[np.ndarray, np.ndarray]:
    """(p, 6) batch-means variance of u along each eigenvector, and the blocks it rests on (p,).

    A block's score is A_b u − b_b = L(u) w_b with w_b the block's 16 terms, A_b = [[n_b I, −M_b],
    [−M_bᵀ, n_b I]]; Σ_b (score)(score)ᵀ = L Σ w wᵀ Lᵀ comes from the accumulator's moments. The sandwich
    A⁻¹ S A⁻¹ along v_k is v_kᵀ S v_k / (n μ_k)², scaled up for frames not yet in a finished block.
    """
    H, covered, blocks = acc.block_moments(P)
    c, l = u[:, None, :3], u[:, None, 3:]
    a, b = V[:, :3, :].transpose(0, 2, 1), V[:, 3:, :].transpose(0, 2, 1)  # (p, 6, 3): v_k = (a_k, b_k)
    # v_kᵀ L, written out: the score's n-term is c n_b on the first half and l n_b on the second; M_b[r, s]
    # enters as −M_b l (row r, −l_s) and −M_bᵀ c (row s, −c_r); the two b halves as −I.
    LV = np.concatenate([
        (a * c).sum(axis=2, keepdims=True) + (b * l).sum(axis=2, keepdims=True),
        -(a[..., :, None] * l[..., None, :] + c[..., :, None] * b[..., None, :]).reshape(len(P), 6, 9),
        -a, -b], axis=2)  # (p, 6, 16)
    s = ((LV @ H) * LV).sum(axis=2)
    enough = (blocks >= 2) & (covered > 0)
    scale = np.where(enough, n / np.where(covered > 0, covered, 1.0) * blocks / np.maximum(blocks - 1.0, 1.0), np.nan)
    return np.maximum(s, 0.0) * scale[:, None] / (n[:, None] * mu) ** 2, blocks


def _upper_chi2_factor(dof: np.ndarray) -> np.ndarray:
    """ν / χ²_ν at 1 − SE_CONFIDENCE (Wilson–Hilferty): a variance read from ν degrees of freedom scaled to
    its one-sided SE_CONFIDENCE upper bound. scipy.stats is not imported for this: it costs the CLI ~0.3 s."""
    k = 2.0 / (9.0 * dof)
    q = dof * np.maximum(1.0 - k - _Z_SE * np.sqrt(k), 0.05) ** 3
    return dof / q
