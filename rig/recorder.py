"""The HDF5 recorder: a runner observer that writes the run file (see shakerlab.runfile)."""
from __future__ import annotations

import numpy as np

from shakerlab.quantities import CONTINUOUS, channel_name
from shakerlab.runfile.writer import NoSpace, RunWriter

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

    ``quantities`` ({"base": "displacement"|"velocity", "tip": ...}, the rig config's sensor
    quantities): a velocity sensor's channel is recorded as measured, ``v_base``/``v_tip``
    (m/s, attributes ``quantity``/``units``), from ``Block.measured``; never the displacement
    the rig integrated from it in real time.
    """

    def __init__(self, path, *, overwrite: bool = False, flush_interval: float = 0.5, fs: float,
                 quantities: dict | None = None, append: bool = False):
        self.writer = RunWriter(path, overwrite=overwrite, flush_interval=flush_interval, append=append)
        self.path = self.writer.path
        self.fs = fs
        # added stages (append) continue the file's sample count: their indices follow its last sample
        self.offset = self.writer.end_index() if append else 0
        quantities = quantities or {}
        self.quantities = {f"x_{p}": q for p, q in quantities.items() if q != "displacement"}
        # channel written per point: (name in the file, where the block holds it)
        self.channels = [(channel_name(f"x_{p}", quantities.get(p, "displacement")), f"x_{p}")
                         for p in ("base", "tip")]
        # the running integral of each velocity channel since the trigger (every block, rests
        # included; trapezoid): its value at a stage's first sample is the dataset's ``start_m``
        self._position = {name: (0.0, None) for name, role in self.channels if name != role}
        self._starts_pending = False
        self.stage = None
        self.discarded = False      # a run that recorded nothing did not replace the existing file
        self.no_space: NoSpace | None = None    # the file system filled up: recording stopped, data kept

    def on_run_start(self, info: dict) -> None:
        w = self.writer
        for key in [k for k in info if k.endswith("_toml")]:
            if info.get(key):
                w.set_text(key, info[key])
        for name, identity in info.get("identities", {}).items():
            settings = info.get("settings", {}).get(name, {})
            w.set_instrument(name, identity=identity, address=str(settings.get("address", "")), settings=settings)
        w.set_attrs(excitation="base", **{k: v for k, v in info.get("attrs", {}).items()})

    def on_stage_begin(self, name: str, settings: dict, index: int) -> None:
        if self.no_space is not None:
            return
        if self.quantities:
            # the velocity is integrated from the start value this recorder keeps (shakerlab.quantities)
            settings = {**settings, "integration": CONTINUOUS}
        self._starts_pending = bool(self.quantities)
        self.stage = self.writer.begin_stage(name, fs=self.fs, start_index=index + self.offset, settings=settings,
                                             quantities=self.quantities)

    def on_block(self, block) -> None:
        starts = self._integrate(block) if self._position else {}
        if self.stage is None or block.stage is None:
            return
        if self._starts_pending:
            for name, x0 in starts.items():
                self.stage.group[name].attrs["start_m"] = x0
            self._starts_pending = False
        values = {"x_base": block.x_base, "x_tip": block.x_tip, **block.measured}
        flags = {"x_base": block.flags_base, "x_tip": block.flags_tip}
        try:
            self.stage.append(block.index0 + self.offset, {name: values[name] for name, _ in self.channels},
                              flags={name: flags[role] for name, role in self.channels})
        except NoSpace as exc:
            # the run stops (the runner ramps down on an observer's error); the file stays whole to
            # its last flush and nothing more is written into it
            self.no_space = exc
            self.writer.abandon()
            self.stage = None
            raise

    def _integrate(self, block) -> dict:
        """Advance the running integrals by this block; return their values at its first sample."""
        dt = 1.0 / self.fs
        out = {}
        for name, (x_last, v_last) in self._position.items():
            v = block.measured[name]
            if not v.size:
                continue
            v = np.where(np.isfinite(v), v, 0.0)
            x0 = 0.0 if v_last is None else x_last + 0.5 * dt * (v_last + v[0])   # 0 at the trigger
            x_end = x0 + 0.5 * dt * float(np.sum(v[:-1] + v[1:]))
            self._position[name] = (x_end, float(v[-1]))
            out[name] = float(x0)
        return out

    def on_setpoint(self, index: int, vpp: float, hz: float, label: str) -> None:
        if self.stage is not None:
            self.stage.add_step(index + self.offset, vpp, hz, label)

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
        record = {**record, "sample_index": record.get("sample_index", 0) + self.offset}
        ds[n] = tuple(record.get(k, np.nan) for k in CONTROL_FIELDS)
        self.writer._maybe_flush()

    def on_stage_end(self, name: str, status: str, summary: dict) -> None:
        if self.stage is not None:
            self.stage.close(status, summary)
            self.stage = None

    def on_event(self, level: str, message: str, run_time: float) -> None:
        if self.no_space is not None:
            return
        self.writer.log(level, message, run_time=run_time + self.offset / self.fs)

    def on_run_end(self, status: str, reason: str) -> None:
        if self.no_space is not None:
            return
        if status != "complete" and self.writer.n_recorded() == 0 and self.path.exists():
            # stopped before a single sample: the file would hold nothing but the error, and the
            # existing file it would replace (--force) may hold a whole run
            self.writer.discard()
            self.discarded = True
            return
        if reason:
            self.writer.set_attrs(end_reason=reason)
        self.writer.close(status)
