"""``velab info``: a readable summary of a run file and its fits (``--json``: one strict JSON document)."""

from __future__ import annotations

import argparse
import sys

from velab.commands.common import add_json_option, write_json
from velab.errors import VelabError


def register(sub) -> None:
    p = sub.add_parser("info", help="summarise a run file and its fits",
                       description="Print what a run file holds: status, timing, rig, manoeuvre, material, events, "
                       "gaps, fits. A damaged file is reported on one line (exit 2); a run whose structure is "
                       "damaged but readable is shown, marked DAMAGED with the reason (exit 2).")
    p.add_argument("runs", nargs="+", help="run files (.h5)")
    add_json_option(p)
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from velab.runfiles import read_run
    from velab.runfiles.summary import as_dict, describe

    if args.json:
        docs, failed = [], 0
        for path in args.runs:
            try:
                run = read_run(path)
                docs.append(as_dict(run))
                failed += _say_damaged(run)
            except VelabError as exc:
                docs.append({"path": str(path), "error": str(exc)})
                print(f"velab: {exc}", file=sys.stderr)
                failed += 1
        write_json(docs[0] if len(docs) == 1 else {"runs": docs})
        return 2 if failed else 0
    damaged = 0
    for i, path in enumerate(args.runs):
        if i:
            print()
        run = read_run(path)
        for line in result_lines(path):  # the result first (velab.fitting.headline)
            print(line)
        print(describe(run))
        for line in joint_lines(path) + sections_lines(path):
            print(line)
        damaged += _say_damaged(run)
    return 2 if damaged else 0


def _say_damaged(run) -> int:
    """One line on stderr for a run whose structure is damaged (velab.runfiles.soundness); 1 if it is."""
    if not run.damage:
        return 0
    print(f"velab: {run.path}: damaged run ({run.damage}); nothing will be written into it", file=sys.stderr)
    return 1


def result_lines(path, width: int = 100) -> list[str]:
    """The headline of each fit stored in the run (velab.fitting.headline), a blank line after; [] without one."""
    from velab.fitting.headline import headline, headline_lines
    from velab.fitting.jointresult import JointResult
    from velab.fitting.results import SweepResult
    from velab.runfiles.summary import read_fits

    out = []
    for name, d in read_fits(path).items():
        if "error" in d or not d.get("models"):
            continue
        try:
            result = (JointResult if d.get("joint") or d.get("fit_kind") == "joint" else SweepResult).from_dict(d)
            lines = headline_lines(headline(result), width)
        except (KeyError, TypeError, ValueError):  # a damaged fit: describe() says so
            continue
        out += [f"{lines[0]} [fit {name}]", *lines[1:], ""]
    return out


def sections_lines(path) -> list[str]:
    """The fits of a run with several transducers (velab.fitting.sections): each section's position and
    how the fitted wall describes it."""
    from velab.runfiles.summary import read_fits

    out = []
    for name, d in read_fits(path).items():
        sections = d.get("sections")
        if not isinstance(sections, list) or not sections:
            continue
        out.append(f"  fit {name}: {len(sections)} sections, best {d.get('best', '?')}")
        out.extend(_section_lines(sections, "the fitted wall"))
    return out


def joint_lines(path) -> list[str]:
    """The joint fits stored in a run (velab fit --joint): which runs they were made with (path and content
    hash), the joint wall, and how this run and the others sat under it."""
    import math

    from velab.runfiles.summary import read_fits

    out = []
    for name, d in read_fits(path).items():
        if d.get("fit_kind") != "joint" and not d.get("joint"):
            continue
        runs = d.get("runs") if isinstance(d.get("runs"), list) else []
        best = next((m for m in d.get("models", []) if m.get("name") == d.get("best")), {})
        a, se = best.get("wave_speed"), best.get("wave_speed_se")
        wall = f"a = {a:.2f} +- {se:.2g} m/s" if isinstance(a, (int, float)) and isinstance(se, (int, float)) else ""
        out.append(f"  joint fit {name}: {len(runs)} runs, best {d.get('best', '?')} {wall}")
        me = d.get("run_index")
        for i, r in enumerate(runs):
            if not isinstance(r, dict):
                continue
            ratio = r.get("noise_ratio")
            ratio = f"F/noise {ratio:.3g}" if isinstance(ratio, (int, float)) and math.isfinite(ratio) else "F/noise -"
            who = "this run" if i == me else "other run"
            out.append(f"    {who}: {r.get('path', '?')} (head sha256 {str(r.get('head_sha256', ''))[:16]}...), "
                       f"Q0 {1e3 * float(r.get('steady_flow_m3_s') or math.nan):.3g} l/s, {ratio}"
                       + (", DISAGREES with the joint wall" if r.get("disagrees") else ""))
            out.extend("  " + line for line in _section_lines(r.get("sections"), "the joint wall"))
    return out


def _section_lines(sections, wall: str) -> list[str]:
    """One line per section of a stored fit (a fit of several transducers, a joint fit's run): its position,
    n and F/noise, and whether it disagrees with ``wall``."""
    import math

    out = []
    for s in sections if isinstance(sections, list) else ():
        if not isinstance(s, dict):
            continue
        ratio = s.get("noise_ratio")
        ratio = f"F/noise {ratio:.3g}" if isinstance(ratio, (int, float)) and math.isfinite(ratio) else "F/noise -"
        x = s.get("position_m")
        x = f"{x:g} m" if isinstance(x, (int, float)) else "? m"
        out.append(f"    section {s.get('name', '?')} at {x}: n {s.get('n', '?')}, {ratio}"
                   + (f", DISAGREES with {wall}" if s.get("disagrees") else ""))
    return out
