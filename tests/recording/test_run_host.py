"""A Run reaches its recorder only through velab.recording.types.RunHost (issue 27: no class spans two
modules): every attribute run.py reads from the recorder is a member of the protocol, none private, and the
Recorder has every member."""

from __future__ import annotations

import ast
import inspect
from pathlib import Path

import velab.recording.run as run_module
from velab.recording.engine import Recorder
from velab.recording.types import RunHost


def _host_members() -> set[str]:
    tree = ast.parse(inspect.getsource(RunHost))
    cls = tree.body[0]
    names = {n.name for n in cls.body if isinstance(n, ast.FunctionDef)}
    names |= {n.target.id for n in cls.body if isinstance(n, ast.AnnAssign)}
    return names


def _recorder_reads() -> set[str]:
    """Attributes read from ``self.rec`` or ``rec`` in run.py."""
    tree = ast.parse(Path(run_module.__file__).read_text())
    out = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Attribute):
            v = node.value
            if (isinstance(v, ast.Attribute) and v.attr == "rec" and isinstance(v.value, ast.Name)
                    and v.value.id == "self") or (isinstance(v, ast.Name) and v.id == "rec"):
                out.add(node.attr)
    return out


def test_a_run_reads_only_the_run_host_interface():
    reads = _recorder_reads()
    assert len(reads) > 10  # (the scan sees the run's use of its recorder)
    assert not {r for r in reads if r.startswith("_")}, "a Run reaches into the recorder's private members"
    assert reads <= _host_members(), f"not in RunHost: {sorted(reads - _host_members())}"


def test_the_recorder_implements_every_run_host_member():
    tree = ast.parse(inspect.getsource(Recorder))
    assigned = set()
    for node in ast.walk(tree):
        targets = node.targets if isinstance(node, ast.Assign) else [node.target] if isinstance(node, ast.AnnAssign) else []
        for t in targets:
            for e in (t.elts if isinstance(t, ast.Tuple) else [t]):
                if isinstance(e, ast.Attribute) and isinstance(e.value, ast.Name) and e.value.id == "self":
                    assigned.add(e.attr)
    missing = sorted(m for m in _host_members() if not hasattr(Recorder, m) and m not in assigned)
    assert not missing, missing
