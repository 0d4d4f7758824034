"""Confidence intervals for every identified parameter (bootstrap ensemble).

    from recon.output_error.uncertainty import parameter_intervals
    unc = parameter_intervals(result.model, run)      # dict, JSON-safe
    unc["intervals"]["k_m"] -> [low, high];  unc["intervals"]["fn_m"]["y^3"] -> [low, high]

Method (the ensembling idea of PySINDy, applied to the fit that produces the
reported numbers). The reported parameters come from the output-error fit
(:mod:`recon.output_error.polish`): the regression rows are the samples of the simulated
minus measured response over the stages that fit used (:func:`fitted_stages`),
weighted and started as in the polish. An ensemble of refits is
made by resampling what is random in those rows:

1. the residual ``r`` at the estimate and the Jacobian ``J`` of the residual
   with respect to every parameter (central differences, 2 simulations per
   parameter) are computed once;
2. output noise: the residual is cut into contiguous blocks (40 per stage:
   far longer than its correlation length, see ``correlation_length`` in the
   result), and each member
   multiplies every block by an independent random sign (a *block wild
   bootstrap*: it keeps the residual's colour and its change of size along an
   amplitude ramp);
3. input noise: the model is driven by a measured input (``u = -x_base''``
   from a Savitzky-Golay derivative of the noisy base channel, or the noisy
   force). Its noise passes through the resonance into the simulated response
   and is the dominant error of the output-error estimate below ~70 dB SNR
   (with the exact input the same fit is ~30 times more accurate). Each member
   therefore also redraws the input noise: white noise at the level the
   differentiation estimated for the channel, through the same filter, and
   the change it makes to the simulated response is added to the member's
   residual (one simulation per member and stage);
4. each member is refitted by one Gauss-Newton step from the estimate,
   ``d = -(J^T J)^-1 J^T r*``, the exact least-squares refit of the
   linearised model;
5. the differentiation filter also attenuates the input's signal, not only its
   noise; that deterministic loss is undone where the input is made
   (:meth:`recon.model.HystereticModel.stage_input`, via
   :func:`recon.differentiation.undo_passband_loss`), so the estimate the
   ensemble is centred on carries no filter bias;
6. the interval is the percentile interval (2.5 % and 97.5 % for 95 %) of
   every parameter over the members.

Cost: ``2 p + 1`` simulations for the Jacobian plus one per member and stage
(default 200 members): a few seconds on a 2 x 20 000-sample run, less than
the output-error polish itself, so it runs by default (``--no-uncertainty``
skips it; ``input_noise=False`` gives the output-noise-only ensemble, which
needs no extra simulation and is far too narrow when the input is noisy).

What the intervals do not hold: the uncertainty of the *choice* of library
terms (a term not selected has no interval), and bias of the estimate beyond
its noise (e.g. when the output-error polish was skipped or stopped early:
``at_optimum`` is false then).
"""
from __future__ import annotations

from dataclasses import asdict, dataclass

import numpy as np

from recon.determinism import single_thread_blas
from recon.estimator.pipeline import reconstruct
from recon.estimator.tuning import DEFAULT_TUNING, EstimatorTuning
from recon.model import HystereticModel
from recon.output_error.problem import OutputError, measured_error
from recon.regression.criteria import decorrelation_lag
from recon.regression.sparse import GroupedSparseSelector
from recon.signals import input_filter
from recon.steps.bouc_wen import extract
from shakerlab.errors import UserFacingError
from shakerlab.run_data import Run

METHOD = ("output-error ensemble: block wild bootstrap of the residual + redrawn input noise, "
          "linearised refit (one Gauss-Newton step per member), centred on the estimate corrected "
          "for the input differentiation filter's passband loss")


@dataclass
class UncertaintySettings:
    n_resamples: int = 200
    level: float = 0.95
    input_noise: bool = True      # redraw the input noise per member (see the module doc)
    stages: tuple | None = None   # None: the stages the output-error polish fitted (see fitted_stages)
    block: int | None = None      # block length in samples (None: stage length / n_blocks)
    n_blocks: int = 40            # blocks per stage when block is None (long blocks keep the residual's colour)
    seed: int = 0

    def to_dict(self) -> dict:
        d = asdict(self)
        d["stages"] = None if self.stages is None else list(self.stages)
        return d


def fitted_stages(model: HystereticModel) -> list[str]:
    """The stages the output-error polish fitted: recorded in the model's provenance when the
    polish says so, else the pipeline's choice (the nonlinear stage from its recorded initial
    state when the model can start from one, the linear and nonlinear stages from rest before)."""
    prov = model.provenance or {}
    info = prov.get("output_error_polish") or {}
    if info.get("stages"):
        return list(info["stages"])
    st = prov.get("settings") or {}
    lin, non = st.get("linear_stage", "linear"), st.get("nonlinear_stage", "nonlinear")
    return [non] if hasattr(model, "stage_start") else [lin, non]


def fitted_tuning(model: HystereticModel) -> EstimatorTuning:
    """The estimator's tuning ``model`` was fitted with (its provenance's settings: the input's band
    and the start state are made as the polish made them), else the defaults."""
    t = ((model.provenance or {}).get("settings") or {}).get("tuning")
    return EstimatorTuning.of(t) if t is not None else DEFAULT_TUNING


class InputNoise:
    """Draws of the noise the stage's input u carries: white noise of the input channel's level
    through the filter that makes u from that channel (recon.signals.InputFilter)."""

    def __init__(self, stage, tuning: EstimatorTuning = DEFAULT_TUNING):
        self.filter = input_filter(stage, tuning=tuning)
        self.n = self.filter.raw.size
        self.info = self.filter.info()

    def __call__(self, rng: np.random.Generator) -> np.ndarray:
        return self.filter(rng.normal(0.0, self.filter.noise_std, self.n))


def _block_ids(sizes: list[int], residuals: list[np.ndarray], s: UncertaintySettings):
    """Block index of every residual row and the block length used per stage."""
    ids, lengths, offset = [], [], 0
    for n, r in zip(sizes, residuals):
        L = int(s.block) if s.block is not None else n // max(s.n_blocks, 1)
        L = int(max(1, min(L, n)))
        lengths.append(L)
        b = np.arange(n) // L
        ids.append(b + offset)
        offset = int(b[-1]) + 1 + offset
    return np.concatenate(ids), lengths, offset


@single_thread_blas
def parameter_intervals(model: HystereticModel, run: Run, settings: UncertaintySettings | None = None) -> dict:
    """Percentile intervals of every parameter of ``model`` fitted on ``run`` (see module doc)."""
    s = settings or UncertaintySettings()
    if not 0.5 < s.level < 1.0:
        raise UserFacingError(f"uncertainty level must be between 0.5 and 1, got {s.level}")
    if s.n_resamples < 50:
        raise UserFacingError(f"uncertainty needs at least 50 resamples, got {s.n_resamples}")
    wanted = list(s.stages) if s.stages is not None else fitted_stages(model)
    names = [n for n in wanted if n in run.stages]
    if not names:
        raise UserFacingError(f"{run.source or 'run'}: none of the fitting stages {wanted} is recorded")
    data, noise = [], []
    tuning = fitted_tuning(model)
    for name in names:
        st = run.stage(name)
        u = model.stage_input(st, tuning=tuning)
        data.append(model.fit_item(st, u, tuning))   # (t from 0, u, y, recorded start), as the polish fits it
        noise.append(InputNoise(st, tuning))
    # the stages weighted as the polish weighted them: by their noise after the two-stage polish
    # (recon.estimator.two_stage), else by their rms
    polished = (model.provenance or {}).get("output_error_polish") or {}
    joint = polished.get("noise_std") and s.stages is None and list(polished.get("stages") or []) == names
    prob = OutputError(model, data, noise=polished["noise_std"] if joint else None)
    keys, x0, scale = prob.keys, prob.x0, prob.scale
    w = prob.row_weights()

    def resid(x):
        m = prob.build(x, values=True)
        out = []
        for d, target, wi in zip(data, prob.targets, w):
            ys = OutputError.item_response(m, d)
            out.append(measured_error(ys, target) * wi)
        return out

    r_parts = resid(x0)
    r0 = np.concatenate(r_parts)
    if not np.all(np.isfinite(r0)):
        raise UserFacingError("uncertainty: the identified model diverges on the fitting stages; no intervals")
    p = len(keys)
    J = np.empty((r0.size, p))
    eps = 1e-5
    for i in range(p):
        step = np.zeros(p)
        step[i] = eps * scale[i]
        rp = np.concatenate(resid(x0 + step))
        rm = np.concatenate(resid(x0 - step))
        if not (np.all(np.isfinite(rp)) and np.all(np.isfinite(rm))):
            raise UserFacingError(f"uncertainty: the model diverges when {keys[i]} is perturbed; no intervals")
        J[:, i] = (rp - rm) / (2 * eps)          # derivative w.r.t. the scaled parameter
    # pseudo-inverse through the SVD of the column-normalised Jacobian
    cn = np.sqrt(np.sum(J * J, axis=0))
    cn[cn == 0] = 1.0
    U, sv, Vt = np.linalg.svd(J / cn, full_matrices=False)
    keep = sv > sv[0] * 1e-10
    cond = float(sv[0] / sv[-1]) if sv[-1] > 0 else float("inf")
    # A @ r = pinv(J) @ r (scaled parameters)
    A = (Vt[keep].T / sv[keep]) @ U[:, keep].T / cn[:, None]
    gradient_step = -(A @ r0) * scale                     # Gauss-Newton step at the estimate
    at_optimum = bool(np.all(np.abs(gradient_step) <= 0.05 * np.maximum(
        np.abs(x0), 1e-12) + 1e-12) or np.linalg.norm(J.T @ r0) <= 1e-6 * np.linalg.norm(J) * np.linalg.norm(r0))
    bid, lengths, nb = _block_ids([d[2].size for d in data], r_parts, s)
    contrib = np.zeros((p, nb))
    Ar = A * r0                                           # p x N, column i scaled by r_i
    for i in range(p):
        contrib[i] = np.bincount(bid, weights=Ar[i], minlength=nb)
    rng = np.random.default_rng(s.seed)
    signs = rng.choice((-1.0, 1.0), size=(nb, s.n_resamples))
    members = x0[:, None] - (contrib @ signs) * scale[:, None]     # p x B
    if s.input_noise:
        m0 = prob.build(x0, values=True)
        base = [OutputError.item_response(m0, d) for d in data]
    if s.input_noise:
        for b in range(s.n_resamples):
            dr = []
            for d, ys0, wi, nm in zip(data, base, w, noise):
                ys = OutputError.item_response(m0, d, d[1] + nm(rng))
                dr.append((ys - ys0) * wi)
            dr = np.concatenate(dr)
            if np.all(np.isfinite(dr)):
                members[:, b] -= (A @ dr) * scale
    a = 100 * (1 - s.level) / 2
    lo, hi = np.percentile(members, [a, 100 - a], axis=1)
    sd = members.std(axis=1, ddof=1)

    def shaped(values):
        out = {k: float(values[i]) if np.ndim(values[i]) == 0 else [float(v) for v in values[i]]
               for i, k in enumerate(keys) if not k.startswith("fn:")}
        out["fn_m"] = {k[3:]: (float(values[i]) if np.ndim(values[i]) == 0 else [float(v) for v in values[i]])
                       for i, k in enumerate(keys) if k.startswith("fn:")}
        return out

    return {
        "method": METHOD,
        "level": s.level,
        "n_resamples": int(s.n_resamples),
        "stages": names,
        "block_samples": dict(zip(names, lengths)),
        "n_blocks": int(nb),
        "correlation_length": {n: decorrelation_lag(r) for n, r in zip(names, r_parts)},
        "intervals": shaped(np.stack([lo, hi], axis=1)),
        "std": shaped(sd),
        "estimate": shaped(x0),
        "at_optimum": at_optimum,
        "jacobian_condition": cond,
        "residual_nrmse": float(np.sqrt(r0 @ r0 / len(data))),
        "settings": s.to_dict(),
        "input_noise": {n: nm.info for n, nm in zip(names, noise)} if s.input_noise else None,
        "n_simulations": 1 + 2 * p + (len(names) * (1 + s.n_resamples) if s.input_noise else 0),
    }


def covers(unc: dict, truth: dict) -> dict:
    """{parameter: bool} whether each true value lies inside its interval.

    ``truth`` is a model's ``to_dict()["parameters"]``. A true fn term the fit did
    not select counts as not covered; a selected term absent from the truth is
    covered when its interval holds 0.
    """
    iv = unc["intervals"]
    out = {}
    for k, v in truth.items():
        if k == "fn_m":
            continue
        if k in iv:
            out[k] = bool(iv[k][0] <= v <= iv[k][1])
    for term in set(truth.get("fn_m", {})) | set(iv.get("fn_m", {})):
        v = truth.get("fn_m", {}).get(term, 0.0)
        lohi = iv.get("fn_m", {}).get(term)
        out[f"fn_m[{term}]"] = bool(lohi is not None and lohi[0] <= v <= lohi[1])
    return out


# ---------------------------------------------------------------------------
# term selection: how stable is the choice of library terms?
# ---------------------------------------------------------------------------

def reconstruct_capturing(run: Run, settings=None):
    """``recon.estimator.pipeline.reconstruct`` and the sparse-selection problem it solved (regression
    matrix, target, column groups, selector options, library; ``ReconResult.selection_problem``)
    for :func:`term_inclusion`, with the terms the reconstruction finally kept."""

    result = reconstruct(run, settings)
    problem = result.selection_problem
    if problem is not None:
        problem = dict(problem, final_terms=sorted(result.model.fn_m))
    return result, problem


def term_inclusion(problem: dict | None, n_models: int = 20, keep: float = 0.8, n_chunks: int = 40,
                   seed: int = 0) -> dict:
    """Inclusion frequency of every fn term over selections on subsampled rows (PySINDy's
    library bagging): the rows of the agent-model regression are cut into ``n_chunks``
    contiguous chunks, each member keeps a random ``keep`` fraction of them (without
    replacement, so the selector's cross-validation sees no duplicated rows) and reruns the
    pipeline's own term selection and extraction."""
    if problem is None:
        return {"available": False, "reason": "this reconstruction has no sparse selection to resample"}

    A, b = problem["A"] if "A" in problem else problem["lib"].build(*problem["signals"])[0], problem["b"]
    n = A.shape[0]
    chunk = np.arange(n) * n_chunks // n
    rng = np.random.default_rng(seed)
    counts: dict[str, int] = {}
    failed = 0
    for _ in range(n_models):
        chosen = rng.choice(n_chunks, size=max(2, int(round(keep * n_chunks))), replace=False)
        rows = np.isin(chunk, chosen)
        try:
            sp = GroupedSparseSelector(problem["groups"], problem["core"], **problem["options"]).fit(A[rows], b[rows])
            terms = extract(problem["lib"], sp.coef, sp.stderr, sp.support).fn
        except Exception:  # noqa: BLE001 - a degenerate subsample counts as a failed member
            failed += 1
            continue
        for t in terms:
            counts[t] = counts.get(t, 0) + 1
    done = max(n_models - failed, 1)
    freq = {t: c / done for t, c in sorted(counts.items(), key=lambda kv: -kv[1])}
    for t in problem["terms"]:
        freq.setdefault(t, 0.0)
    out = {"available": True, "method": "row-subsampled reselection of the library terms (bagging)",
           "n_models": int(n_models), "failed_models": failed, "keep_fraction": keep, "n_chunks": n_chunks,
           "selected": problem["terms"], "inclusion": freq}
    final = problem.get("final_terms")
    if final is not None and final != problem["terms"]:
        out["final_terms"] = final
        out["note"] = ("the reconstruction revised the terms after the sparse selection (e.g. by output error); "
                       "the inclusion frequencies are those of the sparse selection")
    return out
