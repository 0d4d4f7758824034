"""Sub-commands contributed by ``recon`` (see shakerlab.cli). Import-light: heavy imports in handlers."""
from __future__ import annotations


def register(subparsers) -> None:
    """Add this package's sub-commands to the ``shakerlab`` parser."""
    p = subparsers.add_parser(
        "reconstruct",
        help="identify the hysteretic governing equation from a run file",
        description="Reconstruct y'' + c y' + k y + fn(y, y') + z = u with Bouc-Wen z from a run "
                    "(.h5 or .npz with stages 'linear', 'nonlinear', optionally 'validation'). "
                    "Everything is per unit mass.",
    )
    p.add_argument("run", metavar="RUN", help="run file (.h5 or .npz)")
    p.add_argument("--json", action="store_true", help="print one JSON object (machine-readable)")
    p.add_argument("--plots", metavar="DIR", help="write PNG overlays (time history, hysteresis loop) to DIR")
    p.add_argument("--library-order", metavar="Q", type=int, default=5,
                   help="highest monomial degree of fn (default 5)")
    p.add_argument("--save-model", metavar="PATH", help="write the identified model as JSON to PATH")
    p.add_argument("--no-polish", action="store_true", help="skip the output-error polish (equation-error estimate only)")
    p.set_defaults(handler=_reconstruct)


def _clean(obj):
    """JSON-safe copy: numpy scalars to float, NaN/inf to None."""
    import math

    import numpy as np

    if isinstance(obj, dict):
        return {str(k): _clean(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_clean(v) for v in obj]
    if isinstance(obj, np.ndarray):
        return _clean(obj.tolist())
    if isinstance(obj, (np.floating, float)):
        v = float(obj)
        return v if math.isfinite(v) else None
    if isinstance(obj, np.integer):
        return int(obj)
    if isinstance(obj, np.bool_):
        return bool(obj)
    return obj


def _reconstruct(args) -> int:
    import json
    from pathlib import Path

    from shakerlab.errors import UserFacingError
    from shakerlab.run_data import load_run
    from recon.pipeline import ReconSettings, reconstruct

    if args.library_order < 2 or args.library_order > 8:
        raise UserFacingError(f"--library-order must be between 2 and 8, got {args.library_order}")
    run = load_run(args.run)
    result = reconstruct(run, ReconSettings(library_order=args.library_order, polish=not args.no_polish))
    out = result.to_dict()
    if args.plots:
        out["plots"] = [str(p) for p in write_plots(result, run, Path(args.plots))]
    if args.save_model:
        result.model.save(args.save_model)
    if args.json:
        print(json.dumps(_clean(out)))
        return 0
    print(f"{run.source}: {result.model.excitation} excitation, per unit mass")
    print(result.model.equation())
    v = result.validation
    print(f"validation NRMSE on stage {v['stage']!r}: {v['nrmse']:.4g}"
          + (" (no validation stage: fitted stage)" if v.get("fitted_on_validation_stage") else ""))
    d = result.differentiation["nonlinear"]
    print(f"Savitzky-Golay (nonlinear stage): window {d['window']}, order {d['order']}, "
          f"noise level {', '.join(f'{k} {v:.3g}' for k, v in d['noise_level'].items())}")
    print(f"sparse regression: {result.sparse['n_terms']} library terms, threshold {result.sparse['threshold']:.3g}; "
          f"linear step condition number {result.linear.condition_number:.3g}")
    for p in out.get("plots", []):
        print(f"plot: {p}")
    return 0


def write_plots(result, run, outdir):
    from recon.validation import plot_overlay

    paths = []
    names = [n for n in run.stages if n.startswith("validation")] or [result.settings.nonlinear_stage]
    for name in names:
        st = run.stage(name)
        u = result.model.stage_input(st)
        ysim, _, zsim = result.model.simulate(st.t - st.t[0], u)
        paths.append(plot_overlay(outdir / f"{name}.png", st.t, st.y, ysim, z_sim=zsim,
                                  title=f"{name}: measured vs reconstructed (NRMSE {result.validation['per_stage'].get(name, float('nan')):.3g})"))
    sig = result.signals
    st = run.stage(result.settings.nonlinear_stage)
    u = result.model.stage_input(st)
    ysim, _, zsim = result.model.simulate(st.t - st.t[0], u)
    half = (st.t.size - sig["t"].size) // 2
    paths.append(plot_overlay(outdir / "nonlinear_loop.png", sig["t"], sig["y"], ysim[half:half + sig["t"].size],
                              z_meas=sig["z"], z_sim=zsim[half:half + sig["t"].size],
                              title="fitted stage: z from the measurement vs simulated"))
    return paths
