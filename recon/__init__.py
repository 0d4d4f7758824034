"""recon: reconstruction of hysteretic governing equations from recorded runs (a library).

The public API::

    from recon import reconstruct, ReconSettings, diagnose
    from shakerlab.runfile.reader import load_run

    run = load_run("run.h5")
    result = reconstruct(run, ReconSettings(form="weak"))
    print(result.model)                 # the equation, per unit mass
    result.to_dict()                    # parameters, validation, steps, settings
    diagnosis = diagnose(run, baseline=result.model)

The method's steps live one concept per folder: ``differentiation``, ``signals``,
``library/``, ``regression/``, ``steps/``, ``weak/``, ``estimator/``, ``simulation/``,
``output_error/``, ``chain/``, ``benchmark/``, ``diagnosis/``; ground truths for tests
and benches in ``testing/`` (docs/architecture.md).
"""
from recon.diagnosis.diagnose import Diagnosis, diagnose
from recon.estimator.pipeline import reconstruct
from recon.estimator.result import ReconResult, ReconSettings
from recon.model import HystereticModel

__all__ = ["HystereticModel", "ReconResult", "ReconSettings", "reconstruct", "Diagnosis", "diagnose"]
