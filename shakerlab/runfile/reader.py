"""Reading run files: the HDF5 run file (read-only opens) and the ``.npz`` run."""
from __future__ import annotations

import json
import zipfile
from pathlib import Path

import numpy as np

from shakerlab.errors import UserFacingError
from shakerlab.quantities import PREFIX, channel_name, parse_channel
from shakerlab.run_data import BASE, CHANNELS, FORCE, Run, Stage, check_stage_name
from shakerlab.runfile.format import open_read, stage_order, text


def dataset(group, key: str, path) -> np.ndarray:
    """``group[key][:]``, or a UserFacingError naming the file and the dataset (missing or unreadable)."""
    where = f"{group.name.rstrip('/')}/{key}"
    if key not in group:
        raise UserFacingError(f"{path}: dataset {where} is missing (damaged or edited run file)")
    try:
        return group[key][:]
    except (OSError, KeyError, ValueError, TypeError, RuntimeError) as exc:
        raise UserFacingError(f"{path}: dataset {where} cannot be read ({exc}); the file is damaged") from None


def one_dimensional(values: np.ndarray, where: str, path) -> np.ndarray:
    """A sampled channel holds one value per sample: refuse any other shape, naming the dataset."""
    if values.ndim != 1:
        raise UserFacingError(f"{path}: {where} has shape {values.shape}; a channel holds one value per sample "
                              f"(one dimension). The file is refused.")
    return values


def json_attr(obj, key: str, path) -> dict:
    """A JSON attribute (``settings_json``, ``summary_json``) as a dict, or a UserFacingError naming it."""
    raw = text(obj.attrs.get(key, "{}"))
    try:
        value = json.loads(raw)
    except (json.JSONDecodeError, RecursionError) as exc:
        raise UserFacingError(f"{path}: attribute {key!r} of {obj.name} is not valid JSON ({exc})") from None
    if not isinstance(value, dict):
        raise UserFacingError(f"{path}: attribute {key!r} of {obj.name} is not a JSON object "
                              f"(got {type(value).__name__})")
    return value


def damaged(path, exc: Exception) -> UserFacingError:
    return UserFacingError(f"{path}: the run file is damaged and cannot be read ({type(exc).__name__}: {exc})")


def read_run(path: str | Path, stages: list[str] | None = None) -> Run:
    """Read a run file into a :class:`~shakerlab.run_data.Run` (read-only open).

    Every recorded stage is returned (``linear``, ``nonlinear``,
    ``validation``, ``resonance_search``, ...) unless ``stages`` names a
    subset. A stage's ``settings`` holds its recorded settings plus
    ``status``, ``summary``, ``t0`` and ``steps``. Samples flagged by a
    sensor (out of range, signal loss) cannot be used: a stage holding any is
    refused with a message naming the first one.
    """
    path = Path(path)
    try:
        return _read_run(path, stages)
    except (OSError, KeyError, ValueError, TypeError, RuntimeError) as exc:
        raise damaged(path, exc) from None


def _read_run(path: Path, stages: list[str] | None) -> Run:
    with open_read(path) as f:
        entry = f["entry"]
        out: dict[str, Stage] = {}
        names = stage_order(f)
        if stages is not None:
            missing = [s for s in stages if s not in names]
            if missing:
                raise UserFacingError(f"{path}: no stage(s) {', '.join(missing)} (stages: {', '.join(names)})")
            names = [n for n in names if n in stages]
        for name in names:
            check_stage_name(name, path)
            g = entry["stages"][name]
            excitation = text(g.attrs.get("excitation", "base"))
            if excitation not in CHANNELS:
                raise UserFacingError(f"{path}: stage {name!r} has excitation {excitation!r}, expected one of "
                                      f"{', '.join(sorted(CHANNELS))}")
            t = one_dimensional(dataset(g, "time", path), f"dataset {g.name}/time", path)
            if t.size < 2:
                continue  # a stage interrupted before its first block holds nothing to analyse
            stored = [stored_channel(g, role) for role in CHANNELS[excitation]]   # missing: dataset() names it
            stored += list(json.loads(text(g.attrs.get("extra_channels", "[]"))))   # e.g. a component test's command
            channels = {ch: one_dimensional(dataset(g, ch, path), f"dataset {g.name}/{ch}", path) for ch in stored}
            for ch, v in channels.items():
                if v.shape != t.shape:
                    raise UserFacingError(f"{path}: stage {name!r}: dataset {ch!r} holds {v.size} samples, "
                                          f"'time' {t.size}; the file is damaged")
            for ch in stored:
                flags = dataset(g, f"flags_{ch}", path)
                if flags.any():
                    i = int(np.flatnonzero(flags)[0])
                    raise UserFacingError(
                        f"{path}: stage {name!r} channel {ch!r} has {int(np.count_nonzero(flags))} flagged "
                        f"sample(s) (sensor out of range or signal loss), first at sample {i}"
                    )
            settings = json_attr(g, "settings_json", path)
            settings["status"] = text(g.attrs.get("status", ""))
            settings["t0"] = float(g.attrs.get("t0", 0.0))
            settings["summary"] = json_attr(g, "summary_json", path)
            settings["steps"] = [
                {"sample_index": int(r["sample_index"]), "amplitude_vpp": float(r["amplitude_vpp"]),
                 "frequency_hz": float(r["frequency_hz"]), "label": text(r["label"])}
                for r in (dataset(g, "steps", path) if "steps" in g else [])
            ]
            starts = {ch: float(g[ch].attrs["start_m"]) for ch in stored if "start_m" in g[ch].attrs}
            if starts:      # velocity integrated by the recorder since the trigger (shakerlab.quantities)
                settings["integration_start_m"] = starts
            out[name] = Stage(name=name, t=t, channels=channels, excitation=excitation,
                              settings=settings)
        attrs = {k: text(v) if isinstance(v, bytes) else (v.item() if isinstance(v, np.generic) else v)
                 for k, v in entry.attrs.items()}
        attrs["clean_close"] = bool(f.attrs.get("clean_close", False))
        attrs["software_version"] = text(f.attrs.get("software_version", ""))
    if not out:
        raise UserFacingError(f"{path}: the run file holds no recorded samples")
    return Run(stages=out, attrs=attrs, source=str(path))


def stored_channel(group, role: str) -> str:
    """The dataset holding ``role`` in a stage group: ``x_tip``, or ``v_tip`` / ``a_tip`` when the
    sensor reported velocity or acceleration."""
    if role == "force":
        return role
    for q in PREFIX:
        name = channel_name(role, q)
        if name in group:
            return name
    return role      # missing: the caller's KeyError names the displacement channel


def read_events(path: str | Path) -> list[dict]:
    """The event log: dicts with wall_time, run_time, level, message."""
    with open_read(path) as f:
        return [
            {"wall_time": float(r["wall_time"]), "run_time": float(r["run_time"]),
             "level": text(r["level"]), "message": text(r["message"])}
            for r in f["entry/events"][:]
        ]


def read_info(path: str | Path) -> dict:
    """Run-level metadata: attributes, instruments, config texts, stage summaries, results."""
    try:
        return _read_info(path)
    except (OSError, KeyError, ValueError, TypeError, RuntimeError) as exc:
        raise damaged(path, exc) from None


def _read_info(path: str | Path) -> dict:
    with open_read(path) as f:
        entry = f["entry"]
        info = {
            "clean_close": bool(f.attrs.get("clean_close", False)),
            "software_version": text(f.attrs.get("software_version", "")),
            "status": text(entry.attrs.get("status", "")),
            "mode": text(entry.attrs.get("mode", "structure")),
            "config": {k: text(entry["config"][k][()]) for k in entry["config"]},
            "instruments": {},
            "stages": {},
            "results": list(entry["results"]),
        }
        for name, g in entry["instrument"].items():
            info["instruments"][name] = {
                "identity": text(g.attrs.get("identity", "")),
                "address": text(g.attrs.get("address", "")),
                "settings": json_attr(g, "settings_json", path),
            }
        for name in stage_order(f):
            g = entry["stages"][name]
            info["stages"][name] = {
                "status": text(g.attrs.get("status", "")),
                "n_samples": int(g["time"].shape[0]),
                "fs": float(g.attrs.get("fs", 0.0)),
                "t0": float(g.attrs.get("t0", 0.0)),
                "settings": json_attr(g, "settings_json", path),
                "summary": json_attr(g, "summary_json", path),
            }
        return info


def load_npz(path: str | Path) -> Run:
    """Read an ``.npz`` run: arrays named ``<stage>/<channel>`` or ``<stage>_<channel>``.

    Channels per stage: ``t`` plus ``x_base, x_tip`` (base excitation) or
    ``force, x`` (force excitation); a motion channel may be velocity or acceleration
    (``v_tip``, ``a_base``, ``v``, ...).
    """
    path = Path(path)
    if not zipfile.is_zipfile(path):
        raise UserFacingError(f"{path}: not a shakerlab run file (an .npz run is a zip archive of arrays "
                              f"made by numpy.savez; this file is not one)")
    try:
        data = np.load(path, allow_pickle=False)
        grouped: dict[str, dict[str, np.ndarray]] = {}
        for key in data.files:
            for sep in ("/", "_"):
                stage, _, channel = key.partition(sep)
                if channel == "t" or channel == "force" or parse_channel(channel) is not None:
                    grouped.setdefault(stage, {})[channel] = np.asarray(data[key], dtype=float)
                    break
    except Exception as exc:  # noqa: BLE001 - any unreadable file is the user's problem
        reason = ("holds Python objects, which are never loaded" if "pickle" in str(exc)
                  else f"{type(exc).__name__}: {exc}")
        raise UserFacingError(f"{path}: not a shakerlab run file (not a readable .npz of numeric arrays: "
                              f"{reason})") from None
    if not grouped:
        raise UserFacingError(f"{path}: no stage arrays (expected names like 'linear/t', 'linear/x_tip')")
    stages = {}
    for name, ch in grouped.items():
        check_stage_name(name, path)
        for c, v in ch.items():
            one_dimensional(v, f"array {name}/{c}", path)
        if "t" not in ch:
            raise UserFacingError(f"{path}: stage {name!r} has no time array 't'")
        excitation = FORCE if "force" in ch else BASE
        t = ch.pop("t")
        stages[name] = Stage(name=name, t=t, channels=ch, excitation=excitation)
    return Run(stages=stages, source=str(path))


def save_npz(run: Run, path: str | Path) -> None:
    arrays = {}
    for name, st in run.stages.items():
        arrays[f"{name}/t"] = st.t
        for ch, v in st.recorded().items():
            arrays[f"{name}/{ch}"] = v
    np.savez(path, **arrays)


def load_run(path: str | Path) -> Run:
    """Load a run from ``.h5`` (shakerlab run file) or ``.npz``."""
    path = Path(path)
    if not path.exists():
        raise UserFacingError(f"{path}: no such file")
    if path.suffix == ".npz":
        return load_npz(path)
    if path.suffix in (".h5", ".hdf5", ".nxs"):
        return read_run(path)
    raise UserFacingError(f"{path}: unknown run file type {path.suffix!r} (expected .h5 or .npz)")
