"""Least-squares steps the lenslet fits share (:mod:`lfcam.measure.fastfit`,
:mod:`lfcam.measure.overlap`): Levenberg–Marquardt with difference or secant Jacobians,
Gauss–Newton with a fixed Jacobian, the linear step, and the σ of a fitted log distance
(classical or lenslet jackknife). Parameter 0 is always the log distance; residuals are the
lenslets' four moments in a row each (docs/distance.md, "Uncertainty that covers the error",
"Levenberg–Marquardt's repeated trials (stop 48)")."""

from __future__ import annotations

import math

import numpy as np

MAX_ITERATIONS = 12  # Levenberg–Marquardt's iterations, unless the caller says


COMPILED_SUMS = True  # the fit's sums by lfcam.measure.kernels (gram_of, jt_of, sq_of), not
#                       einsum (5-8 × slower on JᵀJ; docs/distance.md, "The fit's sums compiled
#                       (stop 79)")


def sq(r: np.ndarray) -> float:
    """Σ r² of a vector."""
    if COMPILED_SUMS:
        from lfcam.measure.kernels import sq_of  # numba

        return float(sq_of(np.ascontiguousarray(r, dtype=np.float64)))
    return float(np.einsum("i,i->", r, r))


def gram(jac: np.ndarray) -> np.ndarray:
    """JᵀJ of a tall Jacobian."""
    if COMPILED_SUMS:
        from lfcam.measure.kernels import gram_of  # numba

        return gram_of(np.ascontiguousarray(jac, dtype=np.float64))
    return np.einsum("ki,kj->ij", jac, jac)


def jt(jac: np.ndarray, r: np.ndarray) -> np.ndarray:
    """Jᵀr."""
    if COMPILED_SUMS:
        from lfcam.measure.kernels import jt_of  # numba

        return jt_of(np.ascontiguousarray(jac, dtype=np.float64),
                     np.ascontiguousarray(r, dtype=np.float64))
    return np.einsum("ki,k->i", jac, r)


LM_RETRY_MIN_CHANGE = 0.01  # a damped step within this share (in units of the difference steps)
#                             of one that failed is not tried: of 866 such trials on the focus
#                             grids' 108 points and 231 lines, 1 lowered the cost
#                             (docs/distance.md, "Levenberg–Marquardt's repeated trials (stop 48)")


def levenberg_marquardt(fun, q0, steps, max_iter=MAX_ITERATIONS, tol=1e-6, fun_many=None,
                        r0=None, jac0=None, broyden=False, jac_of=None, settle_log=0.0,
                        ftol=0.0, min_trial=0.0, trial_gain=0.0, stop_above=math.inf,
                        first_or_stop=False, pause=None, trial_lateral=0.0,
                        confirm_above=math.inf, confirm_below=math.inf, confirm_jac=None,
                        fail_stop=0.0):
    """Levenberg–Marquardt on ``fun`` with forward differences of size ``steps``.

    ``fun_many`` (optional) evaluates a list of parameter vectors at once, as ``fun`` would
    one by one (the difference Jacobian's columns in one model pass). ``r0`` (optional) is
    ``fun(q0)`` when the caller already has it. ``jac0`` (optional): the Jacobian to start
    from (of a model of the same function with fewer rays), else it is taken by differences.
    ``broyden``: after an accepted step the Jacobian is updated by Broyden's rule (one
    evaluation a step instead of one a parameter more) and taken by differences again only
    when a step fails.

    Returns (q, residual, cost, Jacobian at the last linearisation: with ``broyden``, the
    last one taken by differences or ``jac0``; the secant updates steer the steps only, as
    they leave the σ of a line 2-3× off).

    ``jac_of`` (optional): ``jac_of(q, r)``, the Jacobian at ``q`` (residual ``r``) by the
    caller's own rule, instead of differences. ``settle_log``: after the first iteration, the
    fit ends when an iteration's undamped step would move the log distance ``q[0]`` by less
    than this (its damped trials move it less still). ``ftol``: the fit ends after an
    iteration whose accepted step lowered the cost by less than this share of it.

    A damped trial whose step lies within :data:`LM_RETRY_MIN_CHANGE` of the last failed
    one's (in units of ``steps``) is not evaluated: λ is raised again and the trial counted.
    ``min_trial``, ``trial_gain``: no trial is evaluated whose step moves the log distance by
    less than ``min_trial`` (each other parameter by less than as large a share of its
    difference step) and would lower the cost by less than ``trial_gain`` of it by the linear
    model; the fit ends there (such a step is the model's own ray noise to judge).
    ``trial_lateral`` (optional): with it, a step is that small where its log distance
    moves by less than ``min_trial`` and each other parameter by less than this share of
    its difference step.
    ``stop_above``: the fit ends after an iteration that leaves the cost over this.
    ``first_or_stop``: with ``jac0``, the fit ends where it began when the first step
    evaluated (``jac0``'s own) does not lower the cost.
    ``confirm_above``: with ``broyden``, a fit that a secant Jacobian's step calls settled
    (``settle_log``, or a step under ``tol``) while its misfit (√cost) is over this goes on
    with a Jacobian taken by differences (the secant's distance column can be stale: the step
    it calls short may be long); ``inf``: never. ``confirm_below``: only where the fit's σ of
    the log distance (the last Jacobian taken by differences, the residual where it stands)
    is under this. ``confirm_jac`` (optional): ``confirm_jac(q)``, that Jacobian by the
    caller's rule.
    ``fail_stop``: a trial that does not lower the cost while its step moves the log distance
    by less than this (and, with ``trial_lateral``, each other parameter by less than that
    share of its difference step) ends the fit where it stands: a step that short failing
    is the model's own ray noise, and its damped repeats fail as well (0: never).
    ``pause`` (optional): ``pause(it, q, r, jac)``, called after iteration ``it`` (from 0)
    when another would follow (``jac``: the Jacobian that iteration stepped with); the fit
    ends there when it returns true.
    """
    q = np.asarray(q0, dtype=np.float64)
    r = fun(q) if r0 is None else r0
    f = sq(r)
    lam = 1e-4
    jac = None if jac0 is None else np.array(jac0, dtype=np.float64)
    last = jac
    fresh = jac is None

    def stale() -> bool:  # a secant's verdict read again (confirm_above)
        return bool(not fresh and math.sqrt(f) > confirm_above
                    and log_distance_sigma(last, r) < confirm_below)
    for it in range(max_iter):
        if jac is None:
            jac = jac_of(q, r) if jac_of is not None else fd_jacobian(fun, fun_many, q, r,
                                                                        steps)
            last, fresh = jac, True
        jtj = gram(jac)
        g = jt(jac, r)
        improved = settled = confirm = False
        dq = np.zeros_like(q)
        failed = None  # the last step tried that did not lower the cost (in units of steps)
        for trial in range(5):
            a = jtj + lam * np.diag(np.diag(jtj) + 1e-30)
            try:
                dq = -np.linalg.solve(a, g)
            except np.linalg.LinAlgError:
                lam *= 10
                continue
            if it > 0 and trial == 0 and abs(dq[0]) < settle_log:
                confirm = stale()
                settled = not confirm
                break
            small = (abs(dq[0]) < min_trial
                     and float(np.max(np.abs(dq[1:] / steps[1:]))) < trial_lateral
                     if trial_lateral > 0.0
                     else float(np.max(np.abs(dq / steps))) * steps[0] < min_trial)
            if small and f - sq(r + jac @ dq) < trial_gain * f:
                settled = True
                break
            if failed is not None and (np.linalg.norm(dq / steps - failed)
                                       < LM_RETRY_MIN_CHANGE * np.linalg.norm(failed)):
                # the damping barely changed the step that failed: it would fail again
                lam *= 10
                continue
            r2 = fun(q + dq)
            f2 = sq(r2)
            if f2 < f:
                if broyden:  # the secant of the accepted step
                    jac = jac + np.outer((r2 - r) - jac @ dq, dq) / float(dq @ dq)
                    fresh = False
                settled = f - f2 < ftol * f
                q, r, f = q + dq, r2, f2
                lam = max(lam / 10, 1e-8)
                improved = True
                break
            if first_or_stop and it == 0 and jac0 is not None:
                settled = True  # (jac0's own first step failed: the fit ends where it began)
                break
            if abs(dq[0]) < fail_stop and (trial_lateral <= 0.0 or float(
                    np.max(np.abs(dq[1:] / steps[1:]))) < trial_lateral):
                settled = True
                break
            failed = dq / steps
            lam *= 10
        short = improved and bool(np.all(np.abs(dq) < tol * np.maximum(steps, 1e-12)
                                         / steps[0]))
        if confirm or (short and stale()):
            # a secant's verdict (settled, or a step too short to go on) read again with a
            # Jacobian by differences (confirm_above)
            jac = None if confirm_jac is None else confirm_jac(q)
            if jac is not None:
                last, fresh = jac, True
            continue
        if settled or f > stop_above:  # (a secant Jacobian is not taken again by
            break  #                           differences to confirm it, but as above)
        if not improved and not fresh:
            jac = None  # the updated Jacobian found no descent: take it by differences
            continue
        if not improved or short:
            break
        if pause is not None and it + 1 < max_iter and pause(it, q, r, last):
            break
        if not broyden:
            jac = None
    return q, r, f, last


def fd_jacobian(fun, fun_many, q, r, steps) -> np.ndarray:
    """Forward-difference Jacobian of ``fun`` at ``q`` (value ``r``), steps ``steps``; with
    ``fun_many``, all columns in one call."""
    points = [q + h * e for h, e in zip(steps, np.eye(len(q)), strict=True)]
    values = fun_many(points) if fun_many is not None else [fun(p) for p in points]
    return np.column_stack([(v - r) / h for v, h in zip(values, steps, strict=True)])


def log_distance_sigma(jac: np.ndarray, r: np.ndarray) -> float:
    """σ of the fitted log distance (parameter 0) from the Jacobian ``jac`` and residual ``r``
    at the minimum: the larger of the classical ``s²·(JᵀJ)⁻¹`` (``s² = Σr²/(n − p)``, every
    residual equally noisy) and the lenslet jackknife (:func:`jackknife_variance`).

    The moments are not equally noisy — a bright lenslet's carry more photon noise, the model's
    mismatch gathers on a few — so the classical σ left far, dim sources of the 12-source
    scenes 3–7σ off. The cluster-robust sandwich ``(JᵀJ)⁻¹ (Σ_k g_k g_kᵀ) (JᵀJ)⁻¹``,
    ``g_k = Σ J·r`` over lenslet ``k``'s four moments, that replaced it was still 1.2–3.7× low
    there: the few bright lenslets that fix the distance pull the fit onto their own noise, so
    their residuals show only part of it (docs/distance.md, "Uncertainty that covers the
    error"). ``inf`` when the Jacobian is singular."""
    n, p = jac.shape
    try:
        inv = np.linalg.inv(gram(jac))
    except np.linalg.LinAlgError:
        return math.inf
    classical = sq(r) / max(n - p, 1) * inv[0, 0]
    if n % 4:
        return math.sqrt(max(classical, 0.0))
    return math.sqrt(max(classical, jackknife_variance(jac, r, inv)[0, 0], 0.0))


LEVERAGE_CAP = 0.95  # a lenslet's leverage counted at most this (its residual × ≤ 20)


def jackknife_variance(jac: np.ndarray, r: np.ndarray, inv: np.ndarray) -> np.ndarray:
    """Covariance of the least-squares parameters by the delete-one-lenslet jackknife
    (the cluster "CR3" estimator): ``(K − 1)/K · Σ_k δ_k δ_kᵀ``, ``δ_k`` the change of the
    parameters when lenslet ``k``'s four moments are left out,

        δ_k = (JᵀJ)⁻¹ J_kᵀ (I − H_k)⁻¹ r_k,   H_k = J_k (JᵀJ)⁻¹ J_kᵀ,

    exact for a linear model (Woodbury), one 4×4 eigen-decomposition a lenslet. Against the
    sandwich it undoes the leverage ``H_k`` that shrinks a lenslet's residual below its noise.
    Eigenvalues of ``H_k`` are capped at :data:`LEVERAGE_CAP`: a lenslet that alone fixes a
    parameter does not make the variance infinite."""
    n, p = jac.shape
    k = n // 4
    if COMPILED_SUMS:
        # the lenslets under the cap by a compiled 4 × 4 solve each; the others below
        from lfcam.measure.kernels import gram_of, jackknife_deltas  # numba

        jac_c = np.ascontiguousarray(jac, dtype=np.float64)
        d, capped = jackknife_deltas(jac_c, np.ascontiguousarray(r, dtype=np.float64),
                                     np.ascontiguousarray(inv, dtype=np.float64),
                                     LEVERAGE_CAP)
        if capped.any():
            d[capped] = _capped_deltas(jac_c.reshape(k, 4, p)[capped],
                                       r.reshape(k, 4)[capped], inv)
        return (k - 1) / k * gram_of(d)
    jk = jac.reshape(k, 4, p)
    rk = r.reshape(k, 4)
    h = (jk @ inv) @ jk.transpose(0, 2, 1)
    d = np.empty((k, p))
    # H_k is positive semi-definite: its eigenvalues lie in [0, trace]. Where the trace is
    # under the cap none is capped, and (I − H_k)⁻¹ r_k is a plain solve (a blur of 2 000
    # lenslets: 0.4 ms against 3.2 ms for the eigen-decompositions)
    plain = np.trace(h, axis1=1, axis2=2) < LEVERAGE_CAP
    if plain.any():
        x = np.linalg.solve(np.eye(4) - h[plain], rk[plain, :, None])[..., 0]
        d[plain] = np.einsum("kaq,ka->kq", jk[plain], x) @ inv  # (inv is symmetric)
    if not plain.all():
        d[~plain] = _capped_deltas(jk[~plain], rk[~plain], inv)
    return (k - 1) / k * (d.T @ d)


def _capped_deltas(jk: np.ndarray, rk: np.ndarray, inv: np.ndarray) -> np.ndarray:
    """The jackknife's ``δ_k`` (rows) of lenslets ``jk`` (K, 4, p), ``rk`` (K, 4) whose
    leverage may pass :data:`LEVERAGE_CAP`: ``(I − H_k)⁻¹ r_k`` by ``H_k``'s eigen-decomposition,
    its eigenvalues capped."""
    h = (jk @ inv) @ jk.transpose(0, 2, 1)
    lam, vec = np.linalg.eigh(h)
    shrink = 1.0 / (1.0 - np.minimum(lam, LEVERAGE_CAP))
    x = np.einsum("kab,kb->ka", vec, shrink * np.einsum("kcb,kc->kb", vec, rk))
    return np.einsum("kaq,ka->kq", jk, x) @ inv


def gauss_newton_fixed(fun, q, r, jac, iterations, skip_below=0.0, min_trial=0.0,
                       trusted=0.0):
    """Gauss–Newton with a fixed Jacobian (from the coarse model): one evaluation a step.
    ``skip_below``: a step whose log distance is under this is not taken (nor evaluated): at
    the minimum the misfit no longer falls by a step that small, and such a step was
    evaluated and halved twice: three evaluations for nothing. ``min_trial``: no step, nor a
    halving of one that failed, is evaluated under this log distance: the fit ends there.
    ``trusted``: a first step (not under those) that moves the log distance by no more than
    this is taken without an evaluation and ends the fit, its residual the linear model's
    ``r + J·dq``: with the model's own Jacobian (a line's refit, its fine fit on the cells)
    such a step lowered the misfit at its first try and left none to take (docs/distance.md,
    "The refit's step by its own Jacobian, not evaluated (stop 79)")."""
    f = sq(r)
    jtj = gram(jac)
    try:
        solve = np.linalg.inv(jtj + 1e-9 * np.diag(np.diag(jtj)))
    except np.linalg.LinAlgError:
        return q, r, f
    for it in range(iterations):
        dq = -(solve @ jt(jac, r))
        if abs(dq[0]) < skip_below:
            break
        if it == 0 and min_trial <= abs(dq[0]) <= trusted:
            r = r + np.einsum("ki,i->k", jac, dq)
            return q + dq, r, sq(r)
        lower = False
        for _ in range(3):
            if abs(dq[0]) < min_trial:
                break  # (a step this short is the model's own ray noise to judge)
            r2 = fun(q + dq)
            f2 = sq(r2)
            if f2 < f:
                lower = True
                break
            dq = 0.5 * dq
        if not lower:
            break
        q, r, f = q + dq, r2, f2
        if abs(dq[0]) < 2e-5:
            break
    return q, r, f


def linear_step(jac: np.ndarray, r: np.ndarray) -> tuple[np.ndarray, float] | None:
    """The Gauss–Newton step ``−δ`` on residual ``r`` with Jacobian ``jac`` (``δ`` returned, as
    solved) and the misfit² it would remove by the linear model (``Jᵀr · δ``); ``None`` when
    ``JᵀJ`` is singular."""
    jtj = gram(jac)
    g = jt(jac, r)
    try:
        step = np.linalg.solve(jtj + 1e-9 * np.diag(np.diag(jtj)), g)
    except np.linalg.LinAlgError:
        return None
    return step, float(g @ step)
