"""The HDF5 recorder: a runner observer that writes the run file (see shakerlab.runfile)."""
from __future__ import annotations

import numpy as np

from shakerlab.runfile.writer import RunWriter

# one row per closed-loop analysis window (rig.sine_control), dataset ``control`` of the stage group
CONTROL_FIELDS = ("sample_index", "window_n", "frequency_hz", "target_m", "effective_target_m", "achieved_m",
                  "error_db", "vpp", "setpoint_vpp", "tip_m", "relative_m", "notched", "locked")
CONTROL_DTYPE = np.dtype([("sample_index", "<i8"), ("window_n", "<i8")]
                         + [(k, "<f8") for k in CONTROL_FIELDS[2:11]] + [("notched", "u1"), ("locked", "u1")])


class Recorder:
    """Writes every block of an open stage, the setpoints, the events and the metadata.

    Samples acquired outside a stage (rests between stages) are not written;
    the stage's ``start_index`` and the ``sample_index`` dataset keep the
    common time base.
    """

    def __init__(self, path, *, overwrite: bool = False, flush_interval: float = 0.5, fs: float):
        self.writer = RunWriter(path, overwrite=overwrite, flush_interval=flush_interval)
        self.path = self.writer.path
        self.fs = fs
        self.stage = None
        self.discarded = False      # a run that recorded nothing did not replace the existing file

    def on_run_start(self, info: dict) -> None:
        w = self.writer
        for key in ("rig_toml", "protocol_toml", "simulator_toml"):
            if info.get(key):
                w.set_text(key, info[key])
        for name, identity in info.get("identities", {}).items():
            settings = info.get("settings", {}).get(name, {})
            w.set_instrument(name, identity=identity, address=str(settings.get("address", "")), settings=settings)
        w.set_attrs(excitation="base", **{k: v for k, v in info.get("attrs", {}).items()})

    def on_stage_begin(self, name: str, settings: dict, index: int) -> None:
        self.stage = self.writer.begin_stage(name, fs=self.fs, start_index=index, settings=settings)

    def on_block(self, block) -> None:
        if self.stage is None or block.stage is None:
            return
        self.stage.append(block.index0, {"x_base": block.x_base, "x_tip": block.x_tip},
                          flags={"x_base": block.flags_base, "x_tip": block.flags_tip})

    def on_setpoint(self, index: int, vpp: float, hz: float, label: str) -> None:
        if self.stage is not None:
            self.stage.add_step(index, vpp, hz, label)

    def on_control(self, record: dict) -> None:
        """A closed-loop window: append a row to the stage's ``control`` dataset (created on first use)."""
        if self.stage is None:
            return
        g = self.stage.group
        if "control" not in g:
            ds = g.create_dataset("control", shape=(0,), maxshape=(None,), dtype=CONTROL_DTYPE, chunks=(256,))
            ds.attrs["units"] = ("sample_index: window end (sample number since the trigger); *_m: fundamental "
                                 "peak amplitude, m; error_db: 20 log10(achieved / effective target); vpp: mean "
                                 "generator amplitude over the window, V peak-to-peak")
        ds = g["control"]
        n = ds.shape[0]
        ds.resize((n + 1,))
        ds[n] = tuple(record.get(k, np.nan) for k in CONTROL_FIELDS)
        self.writer._maybe_flush()

    def on_stage_end(self, name: str, status: str, summary: dict) -> None:
        if self.stage is not None:
            self.stage.close(status, summary)
            self.stage = None

    def on_event(self, level: str, message: str, run_time: float) -> None:
        self.writer.log(level, message, run_time=run_time)

    def on_run_end(self, status: str, reason: str) -> None:
        if status != "complete" and self.writer.n_recorded() == 0 and self.path.exists():
            # stopped before a single sample: the file would hold nothing but the error, and the
            # existing file it would replace (--force) may hold a whole run
            self.writer.discard()
            self.discarded = True
            return
        if reason:
            self.writer.set_attrs(end_reason=reason)
        self.writer.close(status)
