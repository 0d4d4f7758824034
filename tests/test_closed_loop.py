"""The closed loop (rig.closed_loop, `shakerlab acquire --diagnose`): the decision, the plan within the
rig's limits and the specimen's ceilings, stages appended to the same run file, the rounds' history,
the cancel. The fast tests give the loop a scripted diagnosis and record on the real simulated rig
(lockstep); the slow one runs the real diagnosis end to end."""
import copy
import json
import shutil

import h5py
import pytest

from recon.diagnosis.ambiguity import separating_stage
from recon.model import HystereticModel
from rig.closed_loop import (STOPS, ClosedLoop, Decision, decide, plan_round, record_round, undecided,
                             unsettled_size)
from rig.config import load_config
from rig.session import acquire, simulated_rig
from shakerlab.cli import main
from shakerlab.runfile.reader import load_run, read_events, read_info
from shakerlab.runfile.results import add_result, read_results
from tests.test_rig_acquisition import rig_config, small_protocol

AMBIGUOUS = {"result": "missing physics: quadratic_damping, coulomb_friction",
             "missing_physics": [{"id": "quadratic_damping", "parameters": {"x:c2": {"value": 0.5}},
                                  "evidence": {"held_out_nrmse_before": 0.02, "held_out_nrmse_after": 0.01}},
                                 {"id": "coulomb_friction", "parameters": {"x:mu": {"value": 0.1}},
                                  "evidence": {"held_out_nrmse_before": 0.02, "held_out_nrmse_after": 0.011}}],
             "ambiguous": ["quadratic_damping", "coulomb_friction"],
             "separating_stage": separating_stage(["quadratic_damping", "coulomb_friction"]),
             "fit_before": {"held_out_nrmse": 0.02}, "fit_after": {"held_out_nrmse": 0.01},
             "candidates_tested": []}
RESOLVED = {**AMBIGUOUS, "result": "missing physics: quadratic_damping", "ambiguous": [], "separating_stage": None,
            "missing_physics": AMBIGUOUS["missing_physics"][:1], "fit_after": {"held_out_nrmse": 0.004}}
CLEAN = {"result": "nothing found", "missing_physics": [], "ambiguous": [], "separating_stage": None,
         "fit_before": {"held_out_nrmse": 0.0012}, "fit_after": {"held_out_nrmse": 0.0012},
         "candidates_tested": [{"id": "coulomb_friction", "significant": False, "explained": 0.0002,
                                "detection_limit": {"parameter": "mu", "value": 0.0046}},
                               {"id": "channel_delay", "significant": False, "explained": 1e-10,
                                "detection_limit": {"parameter": "delay", "value": 1e-5}}]}
HINTED = copy.deepcopy(CLEAN)
HINTED["candidates_tested"][1]["explained"] = 0.3


# ---- the decision and the plan (no rig) -------------------------------------------------------------

def test_decide_stops_or_adds_by_the_answer():
    d = decide(AMBIGUOUS)
    assert d.action == "add" and "ambiguous" in d.reason and d.proposal["stages"] == ["validation_amplitude"]
    assert decide(RESOLVED).stop == "resolved"
    assert decide(CLEAN).stop == "clean" and undecided(CLEAN) == []
    # nothing named, but the record hints at a delay it cannot show: a frequency step
    h = decide(HINTED)
    assert h.action == "add" and "channel_delay" in h.reason and h.proposal["stages"] == ["validation_frequency"]


# a second mode named, whose size the record does not determine: fitted beside the baseline's terms
# as reconstructed its participation was 0.090, with the terms chosen again 0.118 +/- 0.005
UNSETTLED = {**RESOLVED, "result": "missing physics: higher_mode",
             "missing_physics": [{"id": "higher_mode",
                                  "parameters": {"w2": {"value": 377.8, "interval": [377.3, 378.3]},
                                                 "phi2": {"value": 0.118, "interval": [0.1125, 0.1228]}},
                                  "evidence": {"held_out_nrmse_before": 0.0019, "held_out_nrmse_after": 0.0009},
                                  "baseline_terms_revised": {
                                      "moves": [{"move": "swap", "terms": ["y*dy^4", "y^2*dy"]}],
                                      "parameters_before": {"w2": {"value": 377.6, "interval": [377.1, 378.0]},
                                                            "phi2": {"value": 0.090, "interval": [0.085, 0.095]}}}}]}


def test_a_named_effect_whose_size_hangs_on_the_baseline_terms_is_sized_on_a_fitting_stage():
    u = unsettled_size(UNSETTLED["missing_physics"][0])
    assert u == {"parameter": "phi2", "before": 0.090, "after": 0.118, "interval": [0.1125, 0.1228]}
    d = decide(UNSETTLED)
    assert d.action == "add" and d.purpose == "size" and d.proposal["ids"] == ["higher_mode"]
    assert "phi2 moved from 0.09 to 0.118" in d.reason and "fitting stage" in d.reason
    plan = plan_round(d, _info(), load_config(None).limits, 1)
    (st,) = plan.stages
    # named so that the diagnosis fits on it (a stage whose name begins with "validation" is held out)
    assert st.name == "sizing_frequency_r1" and plan.purpose == "size"
    assert st.frequency_hz == pytest.approx(1.3 * 14.26)
    # once per effect: sized already, the answer stands, and the stop says the size still moves
    again = decide(UNSETTLED, sized={"higher_mode"})
    assert again.stop == "resolved" and "still moves with the baseline's terms" in again.reason
    # a value before inside the revised interval: settled, resolved at once
    settled = copy.deepcopy(UNSETTLED)
    settled["missing_physics"][0]["baseline_terms_revised"]["parameters_before"]["phi2"]["value"] = 0.12
    assert unsettled_size(settled["missing_physics"][0]) is None
    assert decide(settled).stop == "resolved" and "still" not in decide(settled).reason
    # no revision, nothing to compare: resolved
    assert unsettled_size(RESOLVED["missing_physics"][0]) is None and decide(RESOLVED).stop == "resolved"
    # undecided first (a held-out stage added to show it), then named: its size came from fitting stages
    # that could not show it, so it is sized too
    assert decide(HINTED).purpose == "show"
    shown = decide(RESOLVED, shown={"quadratic_damping"})
    assert shown.action == "add" and shown.purpose == "size" and "could not show it" in shown.reason
    assert shown.proposal["stages"] == ["validation_amplitude"]      # amplitude-dependent: a second amplitude
    assert decide(RESOLVED, sized={"quadratic_damping"}, shown={"quadratic_damping"}).stop == "resolved"


def test_an_effect_named_only_after_an_added_held_out_round_is_sized(tmp_path, recorded):
    """Nothing named and a delay undecided: a held-out frequency step is added to show it; the
    extended run names a quadratic damping instead, which the record before could not show, so its
    size (fitted on the fitting stages) is measured on a sizing stage next; then resolved. The loop's
    decisions alone (the recorder records nothing: the rig's part is tested above)."""
    import types

    plans = []

    def record(plan):
        plans.append(plan)
        return types.SimpleNamespace(status="complete", reason="")

    path = tmp_path / "run.h5"
    shutil.copy(recorded, path)
    loop = ClosedLoop(path, load_config(None).limits, diagnose=Script(HINTED, RESOLVED), record=record,
                      max_rounds=3)
    result = loop.run()
    assert [r["purpose"] for r in result.rounds] == ["show", "size"]
    assert [p.ids for p in plans] == [["channel_delay"], ["quadratic_damping"]]
    assert "could not show it" in result.rounds[1]["why"]
    assert plans[1].stages[0].name.startswith("sizing_amplitude_r2")
    assert result.stop == "resolved" and "still" not in result.stop_reason
    # an ambiguous pair separated in favour of its runner-up (not named before): sized as well
    second = copy.deepcopy(RESOLVED)
    second["missing_physics"] = [AMBIGUOUS["missing_physics"][1]]
    first = copy.deepcopy(AMBIGUOUS)
    first["missing_physics"] = first["missing_physics"][:1]      # the pair's first named, as diagnose does
    plans.clear()
    loop = ClosedLoop(path, load_config(None).limits, diagnose=Script(first, second), record=record,
                      max_rounds=3)
    assert [r["purpose"] for r in loop.run().rounds] == ["separate", "size"]
    assert plans[1].ids == ["coulomb_friction"]


def test_a_sizing_round_beyond_the_round_limit_leaves_the_answer_resolved(tmp_path, recorded):
    path = tmp_path / "run.h5"
    shutil.copy(recorded, path)
    n = len(read_info(path)["stages"])
    loop, _, _ = _loop(path, load_config(None), Script(UNSETTLED), max_rounds=0)
    result = loop.run()
    assert result.stop == "resolved" and result.rounds == [] and len(read_info(path)["stages"]) == n
    assert "not measured on a stage where it shows" in result.stop_reason and "phi2" in result.stop_reason


def _info(max_vpp=4.0):
    """read_info's shape for a recorded protocol: resonance 14.26 Hz, nonlinear final 4 Vpp at 12.55 Hz."""
    level = {"frequency_hz": 12.55, "amplitude_vpp": 4.0, "peak_base": 1.3e-3, "peak_tip": 5.4e-3,
             "peak_relative": 4.2e-3}
    return {"stages": {
        "resonance_search": {"summary": {"resonance_hz": 14.26, "frequencies_hz": [8.0, 14.26, 24.0],
                                         "base_amplitude_m": [1.3e-5, 7e-6, 1.5e-5],
                                         "transmissibility": [1.5, 23.0, 0.5]},
                             "settings": {"amplitude_vpp": 0.05}},
        "nonlinear": {"summary": {"final_vpp": 4.0, "drive_frequency_hz": 12.55, "levels": [level]},
                      "settings": {"max_vpp": max_vpp}}}}


def test_plan_derives_the_drives_from_the_recorded_run():
    limits = load_config(None).limits
    plan = plan_round(decide(AMBIGUOUS), _info(), limits, 1)
    (st,) = plan.stages
    assert st.name == "validation_amplitude_r1" and not st.refused
    assert st.frequency_hz == pytest.approx(0.88 * 14.26) and st.amplitude_vpp == pytest.approx(0.4 * 4.0)
    assert st.predicted["x_tip"] == pytest.approx(1.2 * 0.4 * 5.4e-3)


def test_a_stage_beyond_a_ceiling_is_refused_and_said_so():
    base = load_config(None).limits
    # the frequency step (1.3 x 14.26 Hz = 18.5 Hz) beyond the rig's drive-frequency limit
    hinted = decide(HINTED)
    plan = plan_round(hinted, _info(), {**base, "max_drive_frequency_hz": 15.0}, 1)
    assert plan.accepted == [] and "rig limit" in plan.stages[0].refused
    assert "max_drive_frequency_hz = 15" in plan.stages[0].refused and "REFUSED" in plan.text()
    # the second amplitude's predicted tip motion beyond the specimen's ceiling (never scaled down)
    plan = plan_round(decide(AMBIGUOUS), _info(), {**base, "max_tip_displacement_m": 0.002}, 1)
    (st,) = plan.stages
    assert st.refused.startswith("specimen ceiling: predicted peak x_tip") and st.amplitude_vpp == pytest.approx(1.6)
    # a level above the first recording's highest one
    plan = plan_round(Decision("add", reason="r", proposal={**separating_stage(["offset", "channel_delay"]),
                                                            "stages": ["validation_frequency"]}),
                      _info(max_vpp=2.0), base, 1)
    assert "[nonlinear] max_vpp = 2" in plan.stages[0].refused


# ---- on the simulated rig -------------------------------------------------------------------------------

@pytest.fixture(scope="module")
def recorded(tmp_path_factory):
    """One small protocol recorded on the simulated rig (copied by each test)."""
    path = tmp_path_factory.mktemp("loop") / "run.h5"
    with simulated_rig(speed=None, seed=5) as (sim, _):
        cfg = rig_config(path.parent, sim)
        outcome = acquire(cfg, small_protocol(), path, lockstep=True)
    assert outcome.status == "complete"
    return path


class Script:
    """A diagnosis that answers from a list (the last answer repeats)."""

    def __init__(self, *answers):
        self.answers = list(answers)
        self.calls = 0

    def __call__(self, path):
        self.calls += 1
        return copy.deepcopy(self.answers[min(self.calls, len(self.answers)) - 1])


def _loop(path, cfg, diagnose, **kw):
    protocol = small_protocol()
    outcomes = []

    def record(plan):
        outcomes.append(record_round(cfg, protocol, path, plan, lockstep=True, observers=kw.pop("observers", [])))
        return outcomes[-1]

    events = []
    loop = ClosedLoop(path, cfg.limits, diagnose=diagnose, record=record,
                      observer=lambda e, p: events.append((e, p)), **kw)
    return loop, outcomes, events


def test_two_rounds_append_to_the_same_file_and_it_opens_everywhere(tmp_path, recorded):
    path = tmp_path / "run.h5"
    shutil.copy(recorded, path)
    before = read_info(path)
    with simulated_rig(speed=None, seed=6) as (sim, _):
        cfg = rig_config(tmp_path, sim)
        loop, outcomes, events = _loop(path, cfg, Script(AMBIGUOUS), max_rounds=2)
        result = loop.run()
    assert result.stop == "max_rounds" and "still: ambiguous" in result.stop_reason
    assert [r["stages_added"] for r in result.rounds] == [["validation_amplitude_r1"], ["validation_amplitude_r2"]]
    assert all(o.status == "complete" for o in outcomes)
    info = read_info(path)
    names = list(info["stages"])
    assert names == list(before["stages"]) + ["validation_amplitude_r1", "validation_amplitude_r2"]
    for name, st in before["stages"].items():        # the first recording is untouched
        assert info["stages"][name]["n_samples"] == st["n_samples"]
        assert info["stages"][name]["t0"] == st["t0"]
    t0 = [info["stages"][n]["t0"] for n in names]
    assert t0 == sorted(t0)                            # added stages continue the run's time base
    added = info["stages"]["validation_amplitude_r1"]
    assert added["status"] == "complete" and added["settings"]["closed_loop_round"] == 1
    assert added["settings"]["drive_vpp"] == pytest.approx(0.4 * before["stages"]["nonlinear"]["summary"]["final_vpp"])
    assert info["clean_close"] and info["status"] == "complete"
    assert "closed_loop_round1_toml" in info["config"] and "protocol_toml" in info["config"]
    assert info["config"]["protocol_toml"] == before["config"]["protocol_toml"]
    # the history, under the run's results
    (group, hist), = [(k, v) for k, v in read_results(path).items() if k.startswith("closed_loop")]
    assert hist["stop"] == "max_rounds" and len(hist["rounds"]) == 2
    assert hist["rounds"][0]["before"]["ambiguous"] == ["quadratic_damping", "coulomb_friction"]
    assert hist["rounds"][0]["after"]["named"][0]["id"] == "quadratic_damping"
    assert [e for e, _ in events].count("recording") == 2
    # the readers of report, reprocess and the GUI
    run = load_run(path)
    assert "validation_amplitude_r2" in run.stages and run.stage("validation_amplitude_r2").t.size > 100
    assert any("closed loop, round 2" in e["message"] for e in read_events(path))
    from rig.gui.results import view_of_run_file

    model = HystereticModel(excitation="base", c_m=3.5, k_m=6000.0, alpha_m=2000.0, gamma=300.0, delta=200.0)
    add_result(path, "reconstruction", {**model.to_dict(), "validation": {}}, text=str(model))
    view = view_of_run_file(path, write_back=False)
    assert view.validation_stage == "validation" and view.overlay is not None
    # a sharp loop (sliding after 3 / (gamma + delta) = 0.06 mm) is read as a friction law in the notes
    sharp = HystereticModel(excitation="base", c_m=3.5, k_m=6000.0, alpha_m=2000.0, gamma=3e4, delta=2e4)
    add_result(path, "reconstruction", {**sharp.to_dict(), "validation": {}}, text=str(sharp))
    notes = view_of_run_file(path, write_back=False).notes
    assert any("friction law" in n and "sliding force 0.04 m/s^2" in n for n in notes), notes


def test_a_sizing_round_records_a_fitting_stage_once(tmp_path, recorded):
    """The loop sizes an unsettled effect once: the stage is recorded under a name the diagnosis fits
    on (its fitting mask covers it, nothing of it is held out), and a second unsettled answer on the
    extended run stops the loop, resolved."""
    from recon.diagnosis.rank import prepare

    path = tmp_path / "run.h5"
    shutil.copy(recorded, path)
    with simulated_rig(speed=None, seed=9) as (sim, _):
        cfg = rig_config(tmp_path, sim)
        loop, outcomes, _ = _loop(path, cfg, Script(UNSETTLED), max_rounds=3)
        result = loop.run()
    assert result.stop == "resolved" and "still moves" in result.stop_reason
    assert result.diagnosis["missing_physics"][0]["id"] == "higher_mode"
    (r,) = result.rounds                             # resolved after one added round
    assert r["purpose"] == "size" and r["stages_added"] == ["sizing_frequency_r1"]
    assert r["before"]["held_out_nrmse_after"] == 0.004 and r["after"]["named"][0]["id"] == "higher_mode"
    assert r["before"]["named"][0]["size_unsettled"]["parameter"] == "phi2"
    info = read_info(path)
    st = info["stages"]["sizing_frequency_r1"]
    assert st["status"] == "complete" and st["settings"]["closed_loop_purpose"] == "size"
    assert "[[fitting_stage]]" in info["config"]["closed_loop_round1_toml"]
    run = load_run(path)
    model = HystereticModel(excitation="base", c_m=3.5, k_m=6000.0, alpha_m=2000.0, gamma=300.0, delta=200.0)
    masks = {d.name: (d.fit, d.held) for d in prepare(run, model)}
    fit, held = masks["sizing_frequency_r1"]
    assert fit.all() and not held.any()
    assert not masks["validation"][0].any()          # the protocol's validation stage stays held out


def test_refused_plan_stops_the_loop_and_records_nothing(tmp_path, recorded):
    path = tmp_path / "run.h5"
    shutil.copy(recorded, path)
    n_before = len(read_info(path)["stages"])
    with simulated_rig(speed=None, seed=8) as (sim, _):
        cfg = rig_config(tmp_path, sim, max_tip_displacement_m=0.0001)
        loop, outcomes, _ = _loop(path, cfg, Script(AMBIGUOUS))
        result = loop.run()
    assert result.stop == "refused" and outcomes == []
    assert result.stop_reason.startswith(STOPS["refused"]) and "specimen ceiling" in result.stop_reason
    assert len(read_info(path)["stages"]) == n_before
    (hist,) = [v for k, v in read_results(path).items() if k.startswith("closed_loop")]
    assert hist["rounds"][0]["plan"]["stages"][0]["refused"].startswith("specimen ceiling")


def test_cancel_stops_cleanly_and_keeps_what_was_recorded(tmp_path, recorded):
    path = tmp_path / "run.h5"
    shutil.copy(recorded, path)
    n_before = len(read_info(path)["stages"])
    holder = {}

    class CancelMidStage:
        """The operator's cancel half-way into the added stage: the loop stops, the runner ramps down."""
        blocks = 0

        def on_block(self, block):
            if block.stage and block.stage.endswith("_r1"):
                self.blocks += 1
                if self.blocks == 20:
                    holder["loop"].cancel()
                    holder["runner"].abort("cancelled by the operator")

    with simulated_rig(speed=None, seed=9) as (sim, _):
        cfg = rig_config(tmp_path, sim)
        protocol = small_protocol()

        def record(plan):
            return record_round(cfg, protocol, path, plan, lockstep=True, observers=[CancelMidStage()],
                                on_runner=lambda r: holder.__setitem__("runner", r))

        loop = ClosedLoop(path, cfg.limits, diagnose=Script(AMBIGUOUS, RESOLVED), record=record)
        holder["loop"] = loop
        result = loop.run()
    assert result.stop == "cancelled" and result.rounds[0]["recording"]["status"] == "aborted"
    info = read_info(path)
    assert len(info["stages"]) == n_before + 1        # the stage cut short is kept
    assert info["stages"]["validation_amplitude_r1"]["status"] == "aborted"
    assert info["clean_close"] and load_run(path).stage("validation_amplitude_r1").t.size > 0
    with h5py.File(path, "r") as f:
        assert f["entry/stages/validation_amplitude_r1/x_tip"].shape[0] > 0
    assert any(k.startswith("closed_loop") for k in read_results(path))

    # a cancel before anything is driven: the loop stops at its next step, nothing is recorded
    path2 = tmp_path / "run2.h5"
    shutil.copy(recorded, path2)
    loop = ClosedLoop(path2, cfg.limits, diagnose=Script(AMBIGUOUS), record=lambda plan: pytest.fail("recorded"),
                      confirm=lambda plan: loop.cancel() or True)
    result = loop.run()
    assert result.stop == "cancelled" and len(read_info(path2)["stages"]) == n_before


def test_declined_plan_is_printed_and_nothing_recorded(tmp_path, recorded):
    path = tmp_path / "run.h5"
    shutil.copy(recorded, path)
    loop = ClosedLoop(path, load_config(None).limits, diagnose=Script(AMBIGUOUS), record=lambda p: pytest.fail(),
                      confirm=lambda plan: False)
    result = loop.run()
    assert result.stop == "declined" and "validation_amplitude_r1" in result.stop_reason


# ---- the command, end to end with the real diagnosis ----------------------------------------------------

# bench/rig_discovery.py's short protocol: a few seconds per stage
SHORT_PROTOCOL = """
[run]
settle_s = 0.5
[linear]
frequency_hz = 8.0
amplitude_vpp = 0.4
duration_s = 2.0
[resonance_search]
start_hz = 8.0
stop_hz = 24.0
steps = 6
refine_steps = 2
amplitude_vpp = 0.05
settle_s = 0.5
measure_s = 0.5
[nonlinear]
frequency_factor = 0.88
start_vpp = 0.5
step_factor = 2.0
max_vpp = 4.0
dwell_s = 1.0
analysis_s = 0.5
hold_s = 2.0
thd_threshold = 0.012
[[validation]]
frequency_factor = 0.7
amplitude_fraction = 1.0
duration_s = 2.0
"""


def rig_toml_1khz(tmp_path):
    """The shipped rig config sampled at 1 kHz (tmp_path/rig.toml), for `acquire --config FILE --simulated`
    and the operator window: a tenth of the samples to simulate, stream and write (a small protocol's
    acquisition 3.5 -> 1.4 CPU-s), where what a test checks does not hang on the sampling rate."""
    from rig.config import DEFAULT_RIG_PATH

    rig = tmp_path / "rig.toml"
    text = DEFAULT_RIG_PATH.read_text().replace("sample_rate_hz = 10000.0", "sample_rate_hz = 1000.0")
    assert "sample_rate_hz = 1000.0" in text, "the shipped rig config no longer names its 10 kHz rate"
    rig.write_text(text)
    return rig


def short_run_args(tmp_path, sim_toml: str, seed: int) -> list[str]:
    """`shakerlab acquire`'s arguments for the short protocol on the in-process simulated rig at 1 kHz,
    with the simulator settings ``sim_toml`` (an effect concealed), into tmp_path/run.h5."""
    rig = rig_toml_1khz(tmp_path)
    proto = tmp_path / "p.toml"
    proto.write_text(SHORT_PROTOCOL)
    sim = tmp_path / "sim.toml"
    sim.write_text(sim_toml)
    return ["acquire", "--config", str(rig), "--simulated", "--protocol", str(proto), "-o", str(tmp_path / "run.h5"),
            "--sim-speed", "0", "--quiet", "--seed", str(seed), "--sim-config", str(sim)]


@pytest.mark.slow
def test_acquire_diagnose_auto_json_end_to_end(tmp_path, capsys):
    """A friction concealed on the simulated rig (--sim-config) at about twice the clean record's
    detection limit: the first diagnosis names nothing but finds friction undecided, the loop records
    a second amplitude into the run file, and the extended run names coulomb_friction with mu within
    10 %. One JSON object on stdout (the final diagnosis with diagnose --json's keys, the rounds); the
    history in the run file, which the readers open. 1 kHz sampling keeps each diagnosis to about a
    minute on two cores (bench/rig_discovery.py --sizes coulomb_friction=0.008 --seed 1: the same case)."""
    out = tmp_path / "run.h5"
    code = main(short_run_args(tmp_path, "[effects]\ncoulomb_friction = 0.008\n", seed=1)
                + ["--diagnose", "--auto", "--json", "--max-rounds", "1"])
    captured = capsys.readouterr()
    assert code == 0, captured.err
    doc = json.loads(captured.out)
    for key in ("baseline", "fit_before", "fit_after", "missing_physics", "result", "candidates_tested",
                "ambiguous", "separating_stage", "warnings"):
        assert key in doc["diagnosis"]
    (r,) = doc["rounds"]
    assert r["before"]["named"] == [] and "coulomb_friction" in r["before"]["undecided"]
    assert r["stages_added"] == ["validation_amplitude_r1"] and r["recording"]["status"] == "complete"
    d = doc["diagnosis"]
    if d["missing_physics"]:
        # named on the extended run, with its size
        assert doc["stop"] == "resolved", doc["stop_reason"]
        (named,) = d["missing_physics"]
        assert named["id"] == "coulomb_friction" and r["after"]["named"][0]["id"] == "coulomb_friction"
        assert named["parameters"]["mu"]["value"] == pytest.approx(0.008, rel=0.1)
    else:
        # or, at twice its detection limit, the added stage shows the friction (its held-out error
        # falls) while the validation stage gets worse beyond its band: "partly explained" by it, the
        # name withheld (recon.diagnosis.stagewise), and the loop stops at its round limit
        p = d["partly_explained"]
        assert p["ids"] == ["coulomb_friction"] and p["worse_on_stages"], p
        stages = p["held_out_stages"]
        amp = stages["validation_amplitude_r1"]
        assert amp["nrmse_after"] < 0.5 * amp["nrmse_before"], amp
        assert doc["stop"] == "max_rounds" and d["result"].startswith("partly explained"), doc["stop_reason"]
    info = read_info(out)
    assert "coulomb_friction = 0.008" in info["config"]["simulator_toml"]
    assert list(info["stages"])[-1] == "validation_amplitude_r1" and info["clean_close"]
    (hist,) = [v for k, v in read_results(out).items() if k.startswith("closed_loop")]
    assert hist["stop"] == doc["stop"] and hist["rounds"][0]["stages_added"] == ["validation_amplitude_r1"]
    assert "validation_amplitude_r1" in load_run(out).stages


# ---- in the operator window ---------------------------------------------------------------------------

@pytest.fixture
def window(qtbot, tmp_path):
    from rig.gui.window import MainWindow
    from tests.test_rig_acquisition import SMALL_PROTOCOL

    # the loop's rounds are scripted: the rig records at 1 kHz (rig_toml_1khz)
    w = MainWindow(config_path=rig_toml_1khz(tmp_path), simulated=True, output_dir=tmp_path / "runs", speed=0.0,
                   seed=2, auto_reconstruct=False)
    qtbot.addWidget(w)
    w.show()
    w.set_protocol_text(SMALL_PROTOCOL, "test protocol")
    yield w
    w.shutdown()


def test_gui_runs_the_loop_after_the_run_and_shows_it(qtbot, window):
    w = window
    w.loop_panel.enabled.setChecked(True)
    w.loop_panel.confirm.setChecked(False)
    w.loop_diagnose = Script(AMBIGUOUS, RESOLVED)
    assert w.start_run(), w.last_error
    qtbot.waitUntil(lambda: w.loop is not None and w.loop.result is not None, timeout=120000)
    p = w.loop_panel
    assert w.loop.result.stop == "resolved"
    assert p.step.text().startswith("stopped (resolved)")
    assert "validation_amplitude_r1" in p.plan.toPlainText() and "ambiguous" in p.plan.toPlainText()
    assert "quadratic_damping: x:c2 = 0.5" in p.named.text()
    assert "0.02" in p.nrmse.text() and "0.004" in p.nrmse.text()
    assert "validation_amplitude_r1" in read_info(w.last_outcome.path)["stages"]
    assert p.diagnose_button.isEnabled() and not p.cancel_button.isEnabled()


def test_gui_cancel_while_a_plan_waits_records_nothing(qtbot, window):
    w = window
    w.loop_panel.confirm.setChecked(True)
    w.loop_diagnose = Script(AMBIGUOUS)
    assert w.start_run(), w.last_error
    qtbot.waitUntil(lambda: w.last_outcome is not None, timeout=120000)
    n = len(read_info(w.last_outcome.path)["stages"])
    assert w.start_loop()
    qtbot.waitUntil(lambda: w.loop_panel.record_button.isEnabled(), timeout=30000)
    assert "REFUSED" not in w.loop_panel.plan.toPlainText()
    qtbot.mouseClick(w.loop_panel.cancel_button, __import__("PySide6").QtCore.Qt.LeftButton)
    qtbot.waitUntil(lambda: w.loop.result is not None, timeout=30000)
    assert w.loop.result.stop == "cancelled" and len(read_info(w.last_outcome.path)["stages"]) == n


def test_acquire_options_and_sim_config(tmp_path, capsys):
    from tests.test_rig_acquisition import SMALL_PROTOCOL

    proto = tmp_path / "p.toml"
    proto.write_text(SMALL_PROTOCOL)
    out = tmp_path / "run.h5"
    assert main(["acquire", "--sim-speed", "0", "--protocol", str(proto), "-o", str(out), "--auto"]) == 2
    assert "--auto applies to --diagnose" in capsys.readouterr().err
    assert main(["acquire", "--config", str(tmp_path / "x.toml"), "--sim-config", str(tmp_path / "s.toml"),
                 "--protocol", str(proto), "-o", str(out)]) == 2
    sim = tmp_path / "sim.toml"
    sim.write_text("[effects]\noffset = 0.5\n")
    assert main(["acquire", "--config", str(rig_toml_1khz(tmp_path)), "--simulated", "--sim-speed", "0",
                 "--protocol", str(proto), "-o", str(out), "--quiet", "--sim-config", str(sim)]) == 0
    assert "with " + str(sim) in capsys.readouterr().out
    assert read_info(out)["config"]["simulator_toml"] == sim.read_text()


def test_acquire_diagnose_prints_the_loop_and_asks_only_on_a_terminal(tmp_path, capsys, monkeypatch):
    """The command's text output with a scripted diagnosis (a real `diagnose --json` answer of a clean
    short run, made ambiguous for the first round): the plan, the rounds, why it stopped, the final
    diagnosis as `diagnose` prints it. Not on a terminal and without --auto, the plan is printed and
    nothing is recorded."""
    import rig.closed_loop
    from pathlib import Path

    from tests.test_rig_acquisition import SMALL_PROTOCOL

    real = json.loads((Path(__file__).parent / "data" / "diagnosis_short_clean.json").read_text())
    first = {**real, "ambiguous": AMBIGUOUS["ambiguous"], "separating_stage": AMBIGUOUS["separating_stage"]}
    script = Script(first, real)
    monkeypatch.setattr(rig.closed_loop, "diagnose_file", lambda path, extra=None: script(path))
    proto = tmp_path / "p.toml"
    proto.write_text(SMALL_PROTOCOL)
    out = tmp_path / "run.h5"
    rig = ["--config", str(rig_toml_1khz(tmp_path)), "--simulated"]       # the diagnosis is scripted
    assert main(["acquire", *rig, "--sim-speed", "0", "--protocol", str(proto), "-o", str(out), "--quiet",
                 "--diagnose", "--auto"]) == 0
    text = capsys.readouterr().out
    assert "round 1: ambiguous: quadratic_damping and coulomb_friction" in text
    assert "validation_amplitude_r1" in text and "added stages: complete" in text
    assert "nothing found" in text and "not seen above (detection limits on this record)" in text
    assert "closed loop stopped (clean)" in text
    assert "validation_amplitude_r1" in read_info(out)["stages"]

    script = Script(first)
    out2 = tmp_path / "run2.h5"
    assert main(["acquire", *rig, "--sim-speed", "0", "--protocol", str(proto), "-o", str(out2), "--quiet",
                 "--diagnose"]) == 0
    text = capsys.readouterr().out
    assert "closed loop stopped (declined)" in text and "validation_amplitude_r1: " in text
    assert list(read_info(out2)["stages"])[-1] == "validation"


def test_a_channel_delay_records_through_the_sensors(tmp_path):
    """A concealed channel delay on the simulated rig: the run records whole (no sample lost at the
    start: only the delayed tip channel's reach into the ring is shortened, once it wrapped)."""
    with simulated_rig(speed=None, seed=5, sim_config={"effects": {"channel_delay": 0.0023}}) as (sim, _):
        cfg = rig_config(tmp_path, sim, sample_rate_hz=10000.0)   # the shipped rate: the delay is 23 samples
        outcome = acquire(cfg, small_protocol(), tmp_path / "run.h5", lockstep=True)
    assert outcome.status == "complete" and outcome.samples_lost == 0, outcome.reason
