"""The tree of a real run file, as docs/run-format.md shows it (so the doc cannot drift).

``python -m velab.runfiles.listing --update docs/run-format.md`` writes a synthetic
run and a simulated recording, lists both and rewrites the doc's layout blocks;
tests/runfiles/test_run_standards.py fails when the doc and the files differ.
"""

from __future__ import annotations

import argparse
import re
import sys
import tempfile
from pathlib import Path

import h5py

from velab.cli import main as velab

# Attributes that HDF5 dimension scales and our own bookkeeping add everywhere.
_HIDDEN_ATTRS = {"units", "long_name", "DIMENSION_LIST", "REFERENCE_LIST", "CLASS", "NAME", "NX_class",
                 "mime_type", "_Netcdf4Dimid", "_Netcdf4Coordinates"}
BEGIN = "<!-- BEGIN generated layout: {} -->"
END = "<!-- END generated layout: {} -->"


def _dtype(ds: h5py.Dataset) -> str:
    s = h5py.check_string_dtype(ds.dtype)
    if s is not None:
        return "str" if s.length is None else f"str[{s.length}]"
    if ds.dtype.kind == "b" or h5py.check_enum_dtype(ds.dtype):
        return "bool"
    return str(ds.dtype)


def _shape(ds: h5py.Dataset) -> str:
    if ds.shape == ():
        return ""
    return "(" + ", ".join("n" if m is None else str(s) for s, m in zip(ds.shape, ds.maxshape)) + ")"


def _attrs(obj) -> str:
    names = sorted(k for k in obj.attrs if k not in _HIDDEN_ATTRS)
    return " ".join(f"@{k}" for k in names)


def _lines(g: h5py.Group, depth: int, out: list[str]) -> None:
    pad = "    " * depth
    for name in sorted(g):
        obj = g[name]
        if isinstance(obj, h5py.Group):
            nx = obj.attrs.get("NX_class", "")
            nx = nx.decode() if isinstance(nx, bytes) else str(nx)
            out.append(f"{pad}{name}/ {nx} {_attrs(obj)}".rstrip())
            if nx == "NXprocess":
                _fit_lines(obj, depth + 1, out)
            else:
                _lines(obj, depth + 1, out)
        else:
            units = obj.attrs.get("units")
            units = f"[{units.decode() if isinstance(units, bytes) else units}]" if units is not None else ""
            scale = " (dimension scale)" if obj.attrs.get("CLASS", b"") in (b"DIMENSION_SCALE", "DIMENSION_SCALE") else ""
            out.append(f"{pad}{name} {_dtype(obj)}{_shape(obj)} {units}{scale} {_attrs(obj)}".rstrip())


def _fit_lines(g: h5py.Group, depth: int, out: list[str]) -> None:
    """A fit's fields are those of the fitter's to_dict(): show the frame, not the fields."""
    pad = "    " * depth
    for name in ("program", "version", "date"):
        if name in g:
            out.append(f"{pad}{name} {_dtype(g[name])}")
    models = [k for k in sorted(g) if isinstance(g[k], h5py.Group) and "model_index" in g[k].attrs]
    if models:
        out.append(f"{pad}<model>/ NXcollection @model_index   one per model ({', '.join(models)}): "
                   "every field of ModelFit.to_dict()")
    out.append(f"{pad}<field>   every other field of SweepResult.to_dict()")


def layout(path: str | Path) -> list[str]:
    with h5py.File(path, "r", locking=False) as fh:
        out = [f"/ {_attrs(fh)}"]
        _lines(fh, 1, out)
    return [re.sub(r"\s+", " ", ln.rstrip()) if not ln.startswith(" ") else
            re.match(r"\s*", ln).group(0) + re.sub(r"\s+", " ", ln.strip()) for ln in out]


def sample_files(folder: str | Path) -> dict[str, Path]:
    """A synthetic run with one fit, and a simulated recording (with its online fit)."""
    folder = Path(folder)
    synth = folder / "synth.h5"
    if velab(["synth", "--duration", "2", "--pretrigger", "0.5", "-o", str(synth)]) != 0:
        raise RuntimeError("velab synth failed")
    if velab(["fit", str(synth), "--models", "0-1", "--window", "1", "--no-polish", "--starts", "1",
             "--name", "NAME"]) != 0:
        raise RuntimeError("velab fit failed")
    rec_dir = folder / "rec"
    rec_dir.mkdir()
    # 6 s after the trigger: the slow channels (polled every 0.15 s of host time, 1.8 s of the fast clock's axis)
    # have at least two readings inside the record on a loaded host (tests/runfiles/test_run_standards.py)
    if velab(["record", "--simulate", "--fast", "--duration", "6", "--window", "1.5", "--models", "0-1",
             "--out-dir", str(rec_dir), "--quiet"]) != 0:
        raise RuntimeError("velab record --simulate failed")
    return {"synth": synth, "recorded": next(rec_dir.glob("*.h5"))}


def blocks(files: dict[str, Path]) -> dict[str, str]:
    return {k: "\n".join(layout(p)) for k, p in files.items()}


def update_doc(doc: Path, generated: dict[str, str]) -> str:
    text = doc.read_text()
    for key, body in generated.items():
        begin, end = BEGIN.format(key), END.format(key)
        pattern = re.compile(re.escape(begin) + r".*?" + re.escape(end), re.S)
        if not pattern.search(text):
            raise ValueError(f"{doc}: no {begin} ... {end} block")
        text = pattern.sub(lambda _: f"{begin}\n```\n{body}\n```\n{end}", text)
    return text


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--update", metavar="DOC", help="rewrite the layout blocks of this markdown file")
    args = ap.parse_args(argv)
    with tempfile.TemporaryDirectory() as d:
        gen = blocks(sample_files(d))
    if args.update:
        Path(args.update).write_text(update_doc(Path(args.update), gen))
    else:
        for key, body in gen.items():
            print(f"# {key}\n{body}\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
