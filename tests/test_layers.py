"""The architecture, asserted: layers, no import cycles, no private names across modules,
no imports inside functions except the documented lazy ones (docs/architecture.md)."""
from __future__ import annotations

import ast
import functools
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
PACKAGES = ("shakerlab", "drivers", "sim_backend", "rig", "recon", "workflows")

# what each package may import (besides itself and third-party code)
ALLOWED = {
    "shakerlab": {"shakerlab"},
    "drivers": {"shakerlab"},
    "sim_backend": {"shakerlab"},
    "rig": {"shakerlab", "drivers"},
    "recon": {"shakerlab"},
    "workflows": {"shakerlab", "recon", "rig", "sim_backend"},
}
# the application's entry points may reach everything (command line, operator window)
ENTRY_POINTS = {
    "shakerlab.cli": set(PACKAGES),
    "rig.gui.window": {"sim_backend", "recon"},
    "rig.gui.results": {"recon"},
    "rig.gui.diagnosis": {"recon"},
    "rig.session": {"sim_backend"},
    "rig.closed_loop": {"recon"},               # the closed loop: acquire, diagnose, acquire again
    "rig.commands": {"workflows"},              # acquire --diagnose prints what `diagnose` prints
}
# a function-local import is allowed only with a one-line reason on the same line ("# heavy: ..." or
# "# lazy: ..."), for start-up time of the command line or the operator window
LAZY_MARKERS = ("# heavy", "# lazy", "# optional")


@functools.lru_cache(maxsize=None)
def _tree(path: Path) -> ast.AST:
    """The parsed source of ``path``, once per test session: the tests below walk every module's tree
    and none changes it."""
    return ast.parse(path.read_text(encoding="utf-8"))


def _modules():
    for pkg in PACKAGES:
        for path in sorted((ROOT / pkg).rglob("*.py")):
            rel = path.relative_to(ROOT).with_suffix("")
            parts = list(rel.parts)
            if parts[-1] == "__init__":
                parts = parts[:-1]
            yield ".".join(parts), path


MODULES = dict(_modules())


def _imports(path: Path):
    """(module imported, names, node, inside a function?) for every import statement."""
    tree = _tree(path)
    funcs = set()
    for node in ast.walk(tree):
        if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
            for sub in ast.walk(node):
                if sub is not node:
                    funcs.add(id(sub))
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            for a in node.names:
                yield a.name, [], node, id(node) in funcs
        elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            yield node.module, [a.name for a in node.names], node, id(node) in funcs


def _first_party(name: str) -> str | None:
    top = name.split(".")[0]
    return top if top in PACKAGES else None


def _resolve(module: str, names: list[str]) -> list[str]:
    """The project modules an import statement loads (``from pkg import mod`` loads pkg.mod)."""
    out = [module] if module in MODULES else []
    for n in names:
        if f"{module}.{n}" in MODULES:
            out.append(f"{module}.{n}")
    return out


def test_every_package_respects_its_layer():
    bad = []
    for mod, path in MODULES.items():
        pkg = mod.split(".")[0]
        allowed = ALLOWED[pkg] | {pkg} | ENTRY_POINTS.get(mod, set())
        for name, _, node, _ in _imports(path):
            top = _first_party(name)
            if top and top not in allowed:
                bad.append(f"{mod}:{node.lineno} imports {name}")
    assert not bad, "layer violations:\n" + "\n".join(bad)


def test_recon_is_a_library_without_application_dependencies():
    bad = []
    for mod, path in MODULES.items():
        if mod.split(".")[0] != "recon":
            continue
        for name, _, node, _ in _imports(path):
            if name.split(".")[0] in ("matplotlib", "dask", "distributed", "argparse", "PySide6", "pyqtgraph"):
                bad.append(f"{mod}:{node.lineno} imports {name}")
    assert not bad, "\n".join(bad)


def test_no_import_cycles():
    graph = {m: set() for m in MODULES}
    for mod, path in MODULES.items():
        for name, names, _, _ in _imports(path):
            for dep in _resolve(name, names):
                if dep != mod and not mod.startswith(dep + "."):   # a package's __init__ is not a cycle
                    graph[mod].add(dep)
    # Tarjan's strongly connected components
    index, low, stack, on, comps, counter = {}, {}, [], set(), [], [0]

    def visit(v):
        index[v] = low[v] = counter[0]
        counter[0] += 1
        stack.append(v)
        on.add(v)
        for w in graph[v]:
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            comp = []
            while True:
                w = stack.pop()
                on.discard(w)
                comp.append(w)
                if w == v:
                    break
            if len(comp) > 1:
                comps.append(sorted(comp))

    for v in graph:
        if v not in index:
            visit(v)
    assert not comps, "import cycles: " + "; ".join(" <-> ".join(c) for c in comps)


def test_no_private_name_is_imported_across_modules():
    bad = []
    for mod, path in MODULES.items():
        for name, names, node, _ in _imports(path):
            if _first_party(name):
                for n in names:
                    if n.startswith("_") and not n.startswith("__"):
                        bad.append(f"{mod}:{node.lineno} imports {name}.{n}")
    assert not bad, "\n".join(bad)


def test_imports_inside_functions_are_only_the_documented_lazy_ones():
    bad = []
    for mod, path in MODULES.items():
        lines = path.read_text(encoding="utf-8").splitlines()
        for name, _, node, inside in _imports(path):
            if inside and not any(m in lines[node.lineno - 1] for m in LAZY_MARKERS):
                bad.append(f"{mod}:{node.lineno} imports {name} inside a function without a reason")
    assert not bad, "\n".join(bad)


def test_importing_recon_loads_no_application_code():
    """In a fresh interpreter, ``import recon`` (the whole public API) loads neither the application
    layer nor matplotlib, Dask or Qt."""
    import subprocess
    import sys

    code = ("import sys, recon; print(sorted({m.split('.')[0] for m in sys.modules} & "
            "{'workflows', 'rig', 'drivers', 'matplotlib', 'dask', 'distributed', 'PySide6', 'pyqtgraph'}))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=ROOT, check=True)
    assert out.stdout.strip() == "[]", out.stdout


def test_the_command_line_does_not_import_scipy_signal_or_stats():
    """scipy.signal and scipy.stats cost about 0.4 CPU-s each to import (most of a short command's
    start-up): the library computes its Savitzky-Golay filters, its Welch spectra and its quantiles
    itself (recon.differentiation, recon.welch, scipy.special), and the few paths that need a
    scipy.signal filter import it where they run. A fresh interpreter that loads recon and the
    command line has loaded neither."""
    import subprocess
    import sys

    code = ("import sys, recon, shakerlab.cli, workflows.handlers; "
            "print(sorted(m for m in ('scipy.signal', 'scipy.stats') if m in sys.modules))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=ROOT, check=True)
    assert out.stdout.strip() == "[]", out.stdout


def test_no_test_imports_bench():
    """The tests import the library (recon.testing holds the stress recordings and rows) and their
    own helpers, never a bench script: nothing under tests/ imports a module of bench/ or puts
    bench/ on sys.path. (Running a bench script as a command, to test its command line, is fine.)"""
    bench = {p.stem for p in (ROOT / "bench").glob("*.py")} | {"bench"}
    bad = []
    for path in sorted((ROOT / "tests").rglob("*.py")):
        text = path.read_text(encoding="utf-8")
        rel = path.relative_to(ROOT)
        for node in ast.walk(ast.parse(text)):
            names = []
            if isinstance(node, ast.Import):
                names = [a.name for a in node.names]
            elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
                names = [node.module]
            for name in names:
                if name.split(".")[0] in bench:
                    bad.append(f"{rel}:{node.lineno} imports {name}")
            # sys.path.insert(..., <anything naming "bench">) / sys.path.append(...)
            if (isinstance(node, ast.Call) and isinstance(node.func, ast.Attribute)
                    and node.func.attr in ("insert", "append", "extend")
                    and isinstance(node.func.value, ast.Attribute) and node.func.value.attr == "path"
                    and "bench" in ast.unparse(node)):
                bad.append(f"{rel}:{node.lineno} puts bench/ on sys.path")
    assert not bad, "\n".join(bad)


def test_no_test_or_bench_rewrites_a_recon_setting():
    """A tuned number is changed by passing settings (recon.diagnosis.settings, ReconSettings), never
    by rewriting a module's constant: no test or bench script monkeypatches an UPPER_CASE attribute
    or assigns one on an imported module (``rank.BURN_IN_DECAYS = 0``)."""
    bad = []
    for path in sorted(list((ROOT / "tests").rglob("*.py")) + list((ROOT / "bench").glob("*.py"))):
        rel = path.relative_to(ROOT)
        for node in ast.walk(_tree(path)):
            if (isinstance(node, ast.Call) and isinstance(node.func, ast.Attribute) and node.func.attr == "setattr"
                    and len(node.args) >= 2 and isinstance(node.args[1], ast.Constant)
                    and isinstance(node.args[1].value, str) and node.args[1].value.isupper()):
                bad.append(f"{rel}:{node.lineno} sets {node.args[1].value}")
            if isinstance(node, ast.Assign):
                for t in node.targets:
                    if isinstance(t, ast.Attribute) and t.attr.isupper() and isinstance(t.value, ast.Name):
                        bad.append(f"{rel}:{node.lineno} assigns {t.value.id}.{t.attr}")
    assert not bad, "\n".join(bad)


def test_the_diagnosis_rule_and_split_live_in_its_settings():
    """No module of recon.diagnosis holds a number of the significance rule, the held-out split, the
    burn-in, the stages' weighting, the search, the location or the wording under a settings field's
    name: those are DiagnosisSettings / SignificanceRule fields, and every field of both is made with
    recon.settings_fields.bounded (a meaning, a unit and a range, so that describe lists it)."""
    import dataclasses

    from recon.diagnosis.settings import describe, DEFAULTS, DiagnosisSettings, SignificanceRule

    for cls in (DiagnosisSettings, SignificanceRule):
        for f in dataclasses.fields(cls):
            if f.name == "rule":
                continue
            m = f.metadata
            assert m.get("meaning") and m.get("unit") and len(m.get("range", ())) == 2, \
                f"{cls.__name__}.{f.name} is not described (meaning, unit, range: settings_fields.bounded)"
    fields = {r["name"].split(".")[-1].upper() for r in describe(DEFAULTS)}
    left = sorted(f"{mod}.{name}" for mod, (name, _, _) in _recon_constants()
                  if mod.startswith("recon.diagnosis") and name in fields)
    assert not left, f"recon.diagnosis still defines {left} (a DiagnosisSettings field)"


# The module-level numbers recon keeps outside its settings objects (recon/testing aside: module doc
# of the test below). None is a tuned choice; each entry says why, its reason starting with one of
# NUMBER_REASONS. A new module-level number is either a field of a settings object (EstimatorTuning,
# DiagnosisSettings, ConstitutiveSettings) or added here with its reason.
RECON_NUMBERS_ALLOWED = {
    ("recon.content_cache", "CAPACITY"): "numerical: how many results of a pure function are kept; a miss only costs "
                                         "the computation, never changes an answer",
    ("recon.simulation.sensitivity", "N_FIXED"): "numerical: the number of fixed features before the fn terms' in "
                                                 "the sensitivity kernel's feature vector",
    # the diagnosis
    ("recon.diagnosis.candidate_fit", "Z95"): "statistical: the two-sided 95 % normal quantile of an interval",
    ("recon.diagnosis.rank", "RESOLUTION_FRACTION"): "physical: no displacement reading resolves better than "
                                                     "1e-5 of its peak (100 dB)",
    ("recon.diagnosis.rank", "DIFF_ORDERS"): "numerical: the difference orders the model-free noise estimate "
                                             "takes the smallest over",
    ("recon.diagnosis.sensitivity", "SEARCH_STEPS"): "numerical: a cap on a bisection that stops at its own "
                                                     "tolerance",
    # the diagnosis's candidates: each module owns its term's starts and physical range (check)
    ("recon.diagnosis.candidates.coulomb_friction", "V0_FACTORS"): "numerical: the starts of the friction's "
                                                                   "smoothing velocity, which the fit then frees",
    ("recon.diagnosis.candidates.coulomb_friction", "V0_LOWEST"): "physical: the smoothing velocity's lower "
                                                                  "bound, 1 % of the slowest stage's rms velocity",
    ("recon.diagnosis.candidates.higher_mode", "ZETA2_RANGE"): "physical: the damping ratios a structural mode "
                                                               "has (0.1 % to 30 %)",
    ("recon.diagnosis.candidates.higher_mode", "MODE_APART"): "physical: a 'second mode' within 20 % of the "
                                                              "fundamental is the fundamental's own band",
    ("recon.diagnosis.candidates.hysteresis", "HYSTERESIS_SPLIT_SHARES"): "numerical: starts of the loop's "
                                                                          "share of the stiffness, fitted from there",
    ("recon.diagnosis.candidates.hysteresis", "HARDENING_LIMIT"): "physical: a loop stiffening more than 10 times "
                                                                  "across the record is a spring (the Bouc-Wen "
                                                                  "benchmark's: 4.4 times)",
    ("recon.diagnosis.candidates.hysteresis", "LOOP_MIN_OPENING"): "physical: a loop that opens by less than 1 % "
                                                                   "across the record is a linear spring",
    # the estimator and what it is made of
    ("recon.differentiation", "ORDERS"): "numerical: the polynomial orders the window search tries (its "
                                         "predicted error decides)",
    ("recon.differentiation", "N_WINDOWS"): "numerical: windows per order on the search's log-spaced grid (its "
                                            "predicted error decides)",
    ("recon.differentiation", "BIAS_BLOCK"): "numerical: spectral lines per block of the bias table (memory only, "
                                             "the same answer)",
    ("recon.estimator.drive", "HP_START_HZ"): "physical: the exciter roll-off's start, far below any structural "
                                              "resonance (the refit frees it)",
    ("recon.estimator.two_stage", "FLOOR_SEED"): "reproducibility: the noise floor's draws are fixed, so the same "
                                                 "record gives the same floor",
    ("recon.input_band", "MIN_SAMPLES"): "statistical: the fewest samples whose upper half (128 coefficients) "
                                         "gives the noise floor as a median",
    ("recon.model", "MAX_TERM_DEGREE"): "numerical: the highest term degree a model file may hold (a parse-time "
                                        "bound no fit reaches)",
    ("recon.model", "MAX_SUBSTEPS"): "numerical: a cap on RK4 sub-steps per sample (a trial resonance above about "
                                     "fs is far from any record)",
    ("recon.output_error.problem", "DIVERGED_RESIDUAL"): "numerical: a diverged trial's residual, 1e4 times any "
                                                         "finite normalised cost",
    ("recon.output_error.problem", "FD_STEP"): "numerical: the forward-difference step of the least-squares "
                                               "Jacobians (about sqrt of the simulation's precision)",
    ("recon.signals", "MEASURED_ORDERS"): "numerical: derivative orders (velocity 1, acceleration 2) of the "
                                          "records judged in velocity, codes not magnitudes",
    ("recon.threads", "MAX_THREADS"): "numerical: the finite differences' thread pool size cap (the same answer "
                                      "on any count)",
    ("recon.progress", "MIN_FRACTION_FOR_ESTIMATE"): "display: below 3 % done, an estimate of the time left is "
                                                     "not shown",
    ("recon.benchmark.single_level", "SNR_DB_DEFAULT"): "statistical: a DFT bin is signal when its power is ten "
                                                        "times its noise (identify's snr_db argument)",
}
NUMBER_REASONS = ("statistical", "numerical", "physical", "display", "reproducibility")


def _is_number(node) -> bool:
    """A literal int or float (signed), a tuple or list of them, or arithmetic of them (``1.0 / 60``)."""
    if isinstance(node, ast.UnaryOp) and isinstance(node.op, (ast.USub, ast.UAdd)):
        return _is_number(node.operand)
    if isinstance(node, ast.Constant):
        return isinstance(node.value, (int, float)) and not isinstance(node.value, bool)
    if isinstance(node, (ast.Tuple, ast.List)):
        return bool(node.elts) and all(_is_number(e) for e in node.elts)
    if isinstance(node, ast.BinOp):
        return _is_number(node.left) and _is_number(node.right)
    return False


def _recon_constants():
    """(module, (NAME, value node, line)) for every module-level UPPER_CASE assignment in recon/
    (recon/testing aside)."""
    for path in sorted((ROOT / "recon").rglob("*.py")):
        rel = path.relative_to(ROOT).with_suffix("")
        if rel.parts[1] == "testing":
            continue
        parts = list(rel.parts[:-1] if rel.parts[-1] == "__init__" else rel.parts)
        mod = ".".join(parts)
        for node in _tree(path).body:
            if isinstance(node, ast.Assign):
                targets, value = node.targets, node.value
            elif isinstance(node, ast.AnnAssign) and node.value is not None:
                targets, value = [node.target], node.value
            else:
                continue
            for t in targets:
                for name in ([t] if isinstance(t, ast.Name) else getattr(t, "elts", [])):
                    if isinstance(name, ast.Name) and name.id.isupper():
                        yield mod, (name.id, value, node.lineno)


def test_no_tuned_constant_outside_a_settings_object():
    """A tuned number of recon lives in a settings object: every module-level UPPER_CASE number (an
    int, a float, signed, a tuple of them or arithmetic of them) in recon/ is in RECON_NUMBERS_ALLOWED
    with the reason it is not a tuned choice (statistical, numerical, physical, display,
    reproducibility); a tuned one is a field of EstimatorTuning (recon.estimator.tuning),
    DiagnosisSettings (recon.diagnosis.settings) or ConstitutiveSettings (recon.constitutive.estimator).

    recon/testing is out of scope: its numbers are the independent test-data generator's own draw
    ranges and settling rules, which describe the generator, not the estimator."""
    found = {(mod, name): line for mod, (name, value, line) in _recon_constants() if _is_number(value)}
    new = sorted(f"{mod}.{name} (line {line})" for (mod, name), line in found.items()
                 if (mod, name) not in RECON_NUMBERS_ALLOWED)
    assert not new, ("module-level numbers in recon that are neither settings fields nor allowed with a "
                     f"reason: {new}")
    stale = sorted(f"{mod}.{name}" for mod, name in RECON_NUMBERS_ALLOWED if (mod, name) not in found)
    assert not stale, f"allowed numbers no longer defined (drop them from the list): {stale}"
    for key, reason in RECON_NUMBERS_ALLOWED.items():
        assert reason.split(":")[0] in NUMBER_REASONS and "\n" not in reason, key


def _recon_names(tree: ast.AST) -> set[str]:
    """The names a file binds to recon modules or to what it imports from them (``import recon.x``,
    ``import recon.x as y``, ``from recon.x import y [as z]``), anywhere in the file."""
    out = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            for a in node.names:
                if a.name == "recon" or a.name.startswith("recon."):
                    out.add(a.asname or a.name.split(".")[0])
        elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module \
                and (node.module == "recon" or node.module.startswith("recon.")):
            out.update(a.asname or a.name for a in node.names)
    return out


def _root_name(node: ast.AST) -> str | None:
    """``a`` of ``a``, ``a.b.c``; None for anything else."""
    while isinstance(node, ast.Attribute):
        node = node.value
    return node.id if isinstance(node, ast.Name) else None


# (test file, attribute) a test may still replace, each with its reason: none
RECON_PATCHES_KEPT: set = set()


def test_no_test_monkeypatches_a_recon_module():
    """Tests use real parts: a failure path is brought about by a real input (a run, a model, the
    settings), never by replacing a recon function. No ``monkeypatch.setattr(X, ...)`` or
    ``setattr(X, ...)`` in tests/ whose X is a recon module or something imported from one (nor a
    ``"recon.…"`` target string). Other packages' seams (rig, workflows, shakerlab) may be patched."""
    bad = []
    for path in sorted((ROOT / "tests").rglob("*.py")):
        rel = path.relative_to(ROOT)
        tree = _tree(path)
        names = _recon_names(tree)
        for node in ast.walk(tree):
            if not (isinstance(node, ast.Call) and node.args):
                continue
            f = node.func
            if not ((isinstance(f, ast.Attribute) and f.attr in ("setattr", "delattr"))
                    or (isinstance(f, ast.Name) and f.id in ("setattr", "delattr"))):
                continue
            target = node.args[0]
            if isinstance(target, ast.Constant) and isinstance(target.value, str):
                hit = target.value == "recon" or target.value.startswith("recon.")
            else:
                hit = _root_name(target) in names
            attr = node.args[1].value if len(node.args) > 1 and isinstance(node.args[1], ast.Constant) else None
            if hit and (rel.as_posix(), attr) not in RECON_PATCHES_KEPT:
                bad.append(f"{rel}:{node.lineno} {ast.unparse(node)[:100]}")
    assert not bad, "tests replace recon parts:\n" + "\n".join(bad)


def _p_literal_indices(tree: ast.AST) -> list[int]:
    """Lines where a name ``P`` is indexed by an integer literal (P[6], P[-1], P[:6])."""
    def literal(node) -> bool:
        if isinstance(node, ast.UnaryOp) and isinstance(node.op, (ast.USub, ast.UAdd)):
            node = node.operand
        return isinstance(node, ast.Constant) and type(node.value) is int

    out = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Subscript) and isinstance(node.value, ast.Name) and node.value.id == "P":
            idx = node.slice
            parts = [idx.lower, idx.upper, idx.step] if isinstance(idx, ast.Slice) else [idx]
            if any(part is not None and literal(part) for part in parts):
                out.append(node.lineno)
    return out


RK4 = "recon.simulation.rk4"


def test_the_kernel_parameter_vector_is_indexed_by_name_outside_the_kernel():
    """The simulation kernel's parameter vector is laid out once (rk4.P_NAMES): outside rk4.py it is
    built by name (rk4.kernel_parameters) and never indexed by a position."""
    bad = [f"{mod}:{line} indexes P by a position"
           for mod, path in MODULES.items() if mod.split(".")[0] == "recon" and mod != RK4
           for line in _p_literal_indices(_tree(path))]
    assert not bad, "\n".join(bad)


def test_the_kernels_read_their_parameter_vector_by_named_indices():
    """rk4's kernels read P through its named indices (I_MU, ...: compile-time constants), no literal."""
    tree = _tree(MODULES[RK4])
    assert not _p_literal_indices(tree), f"{RK4} indexes P by a position at lines {_p_literal_indices(tree)}"
    named = [n for n in ast.walk(tree) if isinstance(n, ast.Subscript) and isinstance(n.value, ast.Name)
             and n.value.id == "P" and isinstance(n.slice, ast.Name) and n.slice.id.startswith("I_")]
    assert named, "the kernels' named reads of P were not found (the check reads nothing)"
