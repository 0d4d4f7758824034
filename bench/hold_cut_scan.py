"""Which stress rows the held-out split of ``recon.diagnosis.rank.hold_cut`` changes.

The split depends on the recording alone, so a row needs no diagnosis to tell: each row's recording
is generated as ``bench/diagnose.py --stress`` generates it, and on every stage that is partly held
out the cut of ``hold_cut`` is compared with the plain 70/30 cut (``fit_cut``). A row printed
"moved" is diagnosed differently from before 2026-12-05 (second); on every other row the split,
and with it the diagnosis, is unchanged.

    python bench/hold_cut_scan.py 844 845 ...      # one line per row: index, moved/same, stage:fitted share
"""
import sys
import warnings

warnings.filterwarnings("ignore")

from diagnose_stress import draw, recording       # noqa: E402  (bench/ on the path, as bench/diagnose.py runs)
from independent_run import to_run                # noqa: E402

from recon.diagnosis import rank                  # noqa: E402


def moved_stages(run) -> list[str]:
    """``stage:fitted share`` for each partly held-out stage of ``run`` whose cut hold_cut moves."""
    out, partly = [], rank.partly_held_stages(run)
    for name in (n for n in run.stages if n in partly):
        y = run.stage(name).y
        cut = rank.hold_cut(y)
        if cut != rank.fit_cut(y.size):
            out.append(f"{name}:{cut / y.size:.3f}")
    return out


if __name__ == "__main__":
    for i in map(int, sys.argv[1:]):
        moved = moved_stages(to_run(recording(draw(i))))
        print(i, "moved" if moved else "same", " ".join(moved), flush=True)
