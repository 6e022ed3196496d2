"""What ``afmdrift diagnose`` finds in the drift itself: cycles, slips, kinks (issue 40).

Run: ``.venv/bin/python benchmarks/bench_discover.py [--seeds N] [--controls N]
[--workers N] [--json FILE]``

Sessions of the second generator (:func:`afmdrift.testing.generate_drift_log`)
with one shape nothing logged drives (:data:`afmdrift.testing.DRIFTGEN_SHAPES`):
a cycle (a sine, or a thermostat's on/off), a slip (within a frame, or over
two frame periods) and a change of the drift rate, ``--seeds`` each, diagnosed
with the model that holds every other effect of the generator (``trend,
thermal``). Controls: the generator's ``none`` sessions (``--controls``), the
shared controls of ``../shared/validation/drift-logs`` and the simulator's
control scenarios (``--sim-seeds`` each, replayed through registration as
``tests/integration/test_diagnose.py`` does; slow).

Per shape: found (a significant discovered candidate of the right kind, a
cycle's period within 15 %, a jump's or a kink's time within one frame
period; "located": the same, or a jump that the plain paragraph names
although adding its term does not help the predictions), and for the cycles the one-step RMS
drop when its term is added (≥ 30 % counts). Controls: false discoveries, a
control session with at least one significant discovered candidate. Targets
(issue 40): found ≥ 80 %, drop ≥ 30 % in ≥ 80 % of the cycles, false
discoveries ≤ 5 % of ≥ 20 controls.
"""

from __future__ import annotations

import os

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import argparse
import json
import sys
import tempfile
import time
from concurrent.futures import ProcessPoolExecutor
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

REPO = Path(__file__).resolve().parents[1]
SHARED = REPO.parent / "shared" / "validation" / "drift-logs"
sys.path.insert(0, str(REPO / "tests" / "integration"))
sys.path.insert(0, str(REPO / "benchmarks"))

from bench_diagnose import _pct  # noqa: E402

#: A discovered time is right within this many frame periods.
FRAMES_WITHIN = 1.0
#: A discovered period is right within this fraction.
PERIOD_WITHIN = 0.15


@dataclass(frozen=True)
class Row:
    source: str
    name: str
    shape: str
    truth: float | None
    found: bool
    found_value: float | None
    located: bool
    top: str
    any_discovered: bool
    any_located: bool
    rmse_nm: float
    rmse_with_nm: float | None
    wall_s: float

    @property
    def control(self) -> bool:
        return self.shape == "none"

    @property
    def drop(self) -> float | None:
        if self.rmse_with_nm is None or not self.rmse_nm:
            return None
        return 1.0 - self.rmse_with_nm / self.rmse_nm


def _discovered(j: dict[str, Any], *, significant: bool = True) -> list[dict[str, Any]]:
    """Discovered candidates: significant ones, or (``significant=False``) also
    a jump the plain paragraph names although adding it does not help."""
    if significant:
        return [c for c in j["candidates"] if c.get("significant") and c.get("discovered")]
    # What the plain paragraph reports: significant, or a jump it names.
    return [
        c
        for c in j["candidates"]
        if c.get("discovered")
        and (c.get("significant") or f"`{c['term']}`" in (j.get("plain_finding") or ""))
    ]


def _right(c: dict[str, Any], truth: dict[str, Any], frame_s: float) -> bool:
    d = c["discovered"]
    if d["kind"] != truth["kind"]:
        return False
    if d["kind"] == "periodic":
        return bool(abs(d["period_s"] / truth["period_s"] - 1.0) <= PERIOD_WITHIN)
    return bool(abs(d["t_s"] - truth["t_s"]) <= FRAMES_WITHIN * frame_s)


def judge(
    source: str, name: str, shape: str, truth: dict[str, Any] | None, j: dict[str, Any],
    frame_s: float, started: float,
) -> Row:  # fmt: skip
    """One diagnosis against the shape it should find (none for a control)."""
    found = _discovered(j)
    seen = _discovered(j, significant=False)
    hit = None
    located = False
    if truth is not None:
        hit = next((c for c in found if _right(c, truth, frame_s)), None)
        located = any(_right(c, truth, frame_s) for c in seen)
    value = None
    if hit is not None:
        d = hit["discovered"]
        value = d.get("period_s", d.get("t_s"))
    top = j["candidates"][0]["effect"] if j["candidates"] else ""
    return Row(
        source=source,
        name=name,
        shape=shape,
        truth=None if truth is None else truth.get("period_s", truth.get("t_s")),
        found=hit is not None,
        found_value=value,
        located=located,
        top=top if j["candidates"] and j["candidates"][0]["significant"] else "",
        any_discovered=bool(found),
        any_located=bool(seen),
        rmse_nm=float(j["rmse_nm"]),
        rmse_with_nm=None if hit is None or hit["rmse_after_nm"] is None
        else float(hit["rmse_after_nm"]),
        wall_s=time.perf_counter() - started,
    )  # fmt: skip


def diagnose_log(source: str, path: str, shape: str, workers: int) -> Row:
    from afmdrift.config import AfmdriftConfig
    from afmdrift.diagnostics import DiagnoseOptions
    from afmdrift.diagnostics._run import diagnose_path

    started = time.perf_counter()
    answer_file = Path(path) / "answer.json"
    answer = json.loads(answer_file.read_text()) if answer_file.is_file() else {}
    dg, data = diagnose_path(
        path,
        config=AfmdriftConfig(),
        effects=["trend", "thermal"],
        options=DiagnoseOptions(workers=workers),
    )
    import numpy as np

    frame_s = float(np.median(np.diff(data.t_s)))
    return judge(source, Path(path).name, shape, answer.get("shape"), dg.to_json(), frame_s,
                 started)  # fmt: skip


def diagnose_sim(case: str, seed: int, workdir: str) -> Row:
    """A simulator control, recorded, replayed and diagnosed as the integration
    test does (its scenario, model and registration)."""
    from test_diagnose import CASES, HIDDEN, small_frames_config

    from afmdrift.diagnostics._run import diagnose_path
    from afmdrift.drivers.sim._record import record_session

    started = time.perf_counter()
    session = Path(workdir) / f"{case}-{seed}"
    record_session(HIDDEN / f"{case}.toml", session, seed=seed)
    dg, _ = diagnose_path(session, config=small_frames_config(), effects=CASES[case])
    return judge("simulator", f"{case}-{seed}", "none", None, dg.to_json(), 1.0, started)


def _table(rows: list[Row]) -> str:
    out = ["shape              sessions  significant   located       drop>=30% of found cycles"]
    for shape in ("cycle", "thermostat", "slip", "slip_two_frames", "rate_change"):
        sel = [r for r in rows if r.shape == shape]
        if not sel:
            continue
        found = [r for r in sel if r.found]
        located = [r for r in sel if r.located]
        dropped = [r for r in found if (r.drop or 0.0) >= 0.30]
        drop = (
            f"{len(dropped)}/{len(found)} {_pct(len(dropped), len(found))}"
            if shape in ("cycle", "thermostat")
            else "-"
        )
        out.append(
            f"{shape:<18} {len(sel):>8}  {len(found):>3}/{len(sel):<3} "
            f"{_pct(len(found), len(sel)):>6}  {len(located):>3}/{len(sel):<3} "
            f"{_pct(len(located), len(sel)):>6}  {drop}"
        )
    controls = [r for r in rows if r.control]
    for source in ("generator", "shared", "simulator", "all"):
        sel = [r for r in controls if source in (r.source, "all")]
        if sel:
            alarms = [r for r in sel if r.any_discovered]
            seen = [r for r in sel if r.any_located]
            out.append(
                f"controls {source:<10} {len(sel):>6}  false discoveries (significant) "
                f"{len(alarms)}/{len(sel)} {_pct(len(alarms), len(sel))}, "
                f"named in the plain paragraph {len(seen)}/{len(sel)} {_pct(len(seen), len(sel))}"
            )
    return "\n".join(out)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--seeds", type=int, default=5, help="seeds per shape")
    ap.add_argument("--controls", type=int, default=20, help="generator control seeds")
    ap.add_argument("--sim-seeds", type=int, default=0, help="seeds per simulator control")
    ap.add_argument("--processes", type=int, default=1, help="sessions diagnosed side by side")
    ap.add_argument("--json", metavar="FILE", help="write every row as JSON")
    a = ap.parse_args()
    from afmdrift.testing import DRIFTGEN_SHAPES, generate_drift_log, write_drift_log

    rows: list[Row] = []
    with tempfile.TemporaryDirectory() as tmp, ProcessPoolExecutor(a.processes) as pool:
        futures = []
        for shape in DRIFTGEN_SHAPES:
            for seed in range(1, a.seeds + 1):
                path = write_drift_log(
                    generate_drift_log(shape, seed), Path(tmp) / f"{shape}-{seed}"
                )
                futures.append(pool.submit(diagnose_log, "generator", str(path), shape, 1))
        for seed in range(1, a.controls + 1):
            path = write_drift_log(generate_drift_log("none", seed), Path(tmp) / f"none-{seed}")
            futures.append(pool.submit(diagnose_log, "generator", str(path), "none", 1))
        if SHARED.is_dir():
            for d in sorted(SHARED.glob("none-*")):
                futures.append(pool.submit(diagnose_log, "shared", str(d), "none", 1))
        for case in ("control", "control_distractors"):
            for seed in range(101, 101 + a.sim_seeds):
                futures.append(pool.submit(diagnose_sim, case, seed, tmp))
        for f in futures:
            r = f.result()
            rows.append(r)
            verdict = "control" if r.control else ("FOUND" if r.found else "missed")
            alarm = " FALSE DISCOVERY" if r.control and r.any_discovered else ""
            drop = "" if r.drop is None else f", drop {100 * r.drop:.0f}%"
            print(
                f"{r.source:<10} {r.name:<24} truth {r.truth!s:<10.8} "
                f"found {r.found_value!s:<10.8} located {r.located!s:<5} top {r.top:<28} "
                f"{verdict}{alarm}{drop} ({r.wall_s:.1f} s)",
                flush=True,
            )
    print()
    print(_table(rows))
    if a.json:
        Path(a.json).write_text(json.dumps([asdict(r) for r in rows], indent=1))


if __name__ == "__main__":
    main()
