"""Generate the student and the solution notebooks from one source each.

Sources: ``notebooks/src/NN_name.py``, jupytext "percent" scripts.  In a code
cell, the lines between ``# BEGIN SOLUTION`` and ``# END SOLUTION`` are the
solution; lines starting ``# STUB: `` right after ``# END SOLUTION`` are the
student's placeholder (without the prefix).  A solution block without
``# STUB:`` lines becomes ``raise NotImplementedError(...)`` and its cell is
tagged ``raises-exception`` in the student version, so a run of the
notebook goes on past it.

Writes ``notebooks/solutions/NN_name.ipynb`` (markers and stubs removed)
and ``notebooks/student/NN_name.ipynb`` (solutions replaced by stubs), both
without outputs.  Needs jupytext and nbformat, not organlab.

Usage::

    python notebooks/build.py            # write both versions of every source
    python notebooks/build.py --check    # exit 1 if a written notebook is out of date
    python notebooks/build.py --force    # also overwrite notebooks edited in Jupyter

Freshness compares only what build.py writes: each cell's type, source and
tags, in order, and the notebook's ``organlab`` metadata.  What Jupyter adds
when it opens, runs or autosaves a notebook (kernelspec, language_info,
execution counts, outputs, widget state, cell ids and UI metadata) is not
compared.  ``metadata.organlab.built`` is a digest of the built cells, so
build.py can tell a notebook edited in Jupyter (its cells no longer match the
digest) from one whose source changed: it never overwrites the former
without ``--force``.
    python notebooks/build.py --pictures docs/img   # run the solutions, save each one's key picture

The key picture of a notebook is the first PNG output of its cell tagged
``key-picture``; ``--pictures`` runs the solution versions (nbclient, the
current interpreter's kernel) and writes ``DIR/notebook_NN_name.png``.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import sys
from pathlib import Path

HERE = Path(__file__).resolve().parent
SRC = HERE / "src"
VERSIONS = ("solutions", "student")
BEGIN, END, STUB = "# BEGIN SOLUTION", "# END SOLUTION", "# STUB: "
RAISES = "raises-exception"


class BuildError(ValueError):
    pass


def split_solution(source, *, where="cell"):
    """Return ``(solution_source, student_source, raises)`` of one code cell's source."""
    sol, stu = [], []
    raises = False
    lines = source.split("\n")
    i = 0
    while i < len(lines):
        line = lines[i]
        if line.strip() != BEGIN:
            if line.strip().startswith(END) or line.lstrip().startswith(STUB):
                raise BuildError(f"{where}: '{line.strip()}' without a '{BEGIN}' before it")
            sol.append(line)
            stu.append(line)
            i += 1
            continue
        indent = line[: len(line) - len(line.lstrip())]
        j = i + 1
        while j < len(lines) and lines[j].strip() != END:
            if lines[j].strip() == BEGIN:
                raise BuildError(f"{where}: nested '{BEGIN}'")
            sol.append(lines[j])
            j += 1
        if j == len(lines):
            raise BuildError(f"{where}: '{BEGIN}' without '{END}'")
        k = j + 1
        stubs = []
        while k < len(lines) and lines[k].lstrip().startswith(STUB):
            stubs.append(indent + lines[k].lstrip()[len(STUB):])
            k += 1
        if not stubs:
            stubs = [indent + 'raise NotImplementedError("exercise: write your solution here")']
            raises = True
        stu.extend(stubs)
        i = k
    return "\n".join(sol), "\n".join(stu), raises


def build_one(path):
    """Both versions of one source: ``{"solutions": nb, "student": nb}``."""
    import jupytext
    import nbformat

    src = jupytext.read(path, fmt="py:percent")
    out = {}
    for version in VERSIONS:
        nb = nbformat.v4.new_notebook(metadata={
            "kernelspec": {"name": "python3", "display_name": "Python 3", "language": "python"},
            "language_info": {"name": "python"},
            "organlab": {"source": f"src/{path.name}", "version": version},
        })
        for n, cell in enumerate(src.cells):
            tags = list(cell.metadata.get("tags", []))
            if "needs-person" in tags:
                raise BuildError(f"{path.name}: cell {n}: 'needs-person' cells are gone: every cell runs under Run All; "
                                 "guard a real-rig cell with a flag set in the first cells (RIG_ATTACHED = False)")
            if cell.cell_type == "code":
                sol, stu, raises = split_solution(cell.source, where=f"{path.name}: cell {n}")
                text = sol if version == "solutions" else stu
                if version == "student" and raises:
                    tags.append(RAISES)
                new = nbformat.v4.new_code_cell(text)
            elif cell.cell_type == "markdown":
                new = nbformat.v4.new_markdown_cell(cell.source)
            else:
                new = nbformat.v4.new_raw_cell(cell.source)
            if tags:
                new.metadata["tags"] = tags
            new.id = f"c{n:03d}"
            nb.cells.append(new)
        nb.metadata["organlab"]["built"] = digest(nb)
        nbformat.validate(nb)
        out[version] = nb
    return out


def controlled(nb):
    """What build.py writes of a notebook and Jupyter leaves alone: ``[(cell_type, source, tags), ...]``."""
    return [(c.cell_type, c.source, tuple(c.get("metadata", {}).get("tags", []))) for c in nb.cells]


def digest(nb):
    """A short digest of :func:`controlled` (stored in ``metadata.organlab.built``)."""
    text = json.dumps(controlled(nb), ensure_ascii=False)
    return hashlib.sha256(text.encode()).hexdigest()[:16]


def compare(written, built):
    """Why a written notebook is not what build.py makes of its source: ``(state, detail)``.

    ``state`` is ``"fresh"``, ``"edited"`` (its cells differ from the digest
    they were built with: someone's work, never overwritten without --force) or
    ``"stale"`` (untouched since built, but its source changed).
    """
    ours, theirs = controlled(written), controlled(built)
    meta = dict(written.metadata.get("organlab", {}))
    if ours == theirs and meta == dict(built.metadata["organlab"]):
        return "fresh", ""
    if meta.get("built") != digest(written):
        return "edited", _first_difference(ours, theirs) or "metadata.organlab"
    return "stale", _first_difference(ours, theirs) or "metadata.organlab"


def _first_difference(ours, theirs):
    for n, (a, b) in enumerate(zip(ours, theirs)):
        if a != b:
            what = "type" if a[0] != b[0] else "source" if a[1] != b[1] else "tags"
            return f"cell {n + 1} ({what})"
    if len(ours) != len(theirs):
        return f"{len(ours)} cells, the source makes {len(theirs)}"
    return ""


def target(version, source):
    return HERE / version / (Path(source).stem + ".ipynb")


def sources():
    return sorted(SRC.glob("[0-9][0-9]_*.py"))


def render(nb):
    import nbformat

    return nbformat.writes(nb) + "\n"


def notebook_client(nb, cwd, *, timeout=600, **options):
    """An nbclient ``NotebookClient`` running ``nb`` in the current interpreter's kernel, in folder ``cwd``.

    nbclient's stand-in for a frontend's Output widget sends every output
    back to the kernel on the shell socket while the client waits on that
    socket for the cell's reply; the wake-up can be lost, and the reply is
    then seen only when the cell's timeout ends (jupyter/nbclient#312:
    measured here as 300 s stalls of the calibration checker's cell, one run
    in three, on a loaded machine).  The stand-in used here records the
    outputs (widget state) without echoing them: no notebook reads an Output
    widget's outputs back in the kernel.
    """
    import nbclient
    from nbclient.output_widget import OutputWidget

    class _RecordingOutput(OutputWidget):
        def sync_state(self):
            pass

    client = nbclient.NotebookClient(nb, timeout=timeout, kernel_name="python3",
                                     resources={"metadata": {"path": str(cwd)}}, **options)
    client.widget_registry["@jupyter-widgets/output"] = {"OutputModel": _RecordingOutput}
    return client


def key_pictures(out_dir, *, timeout=600):
    """Execute every solution notebook and write the PNG of its ``key-picture`` cell; returns the paths."""
    import base64

    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    written = []
    for path in sources():
        nb = build_one(path)["solutions"]
        notebook_client(nb, target("solutions", path).parent, timeout=timeout).execute()
        pngs = [o["data"]["image/png"] for c in nb.cells if "key-picture" in c.metadata.get("tags", [])
                for o in c.get("outputs", []) if "image/png" in o.get("data", {})]
        if not pngs:
            raise BuildError(f"{path.name}: no cell tagged key-picture drew a picture")
        dest = out_dir / f"notebook_{path.stem}.png"
        dest.write_bytes(base64.b64decode(pngs[0]))
        written.append(dest)
        print(f"wrote {dest}")
    return written


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--check", action="store_true", help="exit 1 if a written notebook differs from its source")
    ap.add_argument("--force", action="store_true",
                    help="also overwrite notebooks edited in Jupyter (their cells differ from what build.py wrote)")
    ap.add_argument("--pictures", metavar="DIR", help="execute the solution notebooks and save their key pictures in DIR")
    args = ap.parse_args(argv)
    if args.pictures:
        key_pictures(args.pictures)
        return 0
    return freshen(HERE, check=args.check, force=args.force)


def freshen(root, *, check=False, force=False, say=print):
    """Write (or with ``check`` compare) the notebooks under ``root`` (a notebooks/ folder); the exit status."""
    import nbformat

    root = Path(root)
    stale, edited = [], []
    for path in sorted((root / "src").glob("[0-9][0-9]_*.py")):
        for version, nb in build_one(path).items():
            dest = root / version / (path.stem + ".ipynb")
            rel = f"{root.name}/{version}/{dest.name}"
            state, detail = ("missing", "") if not dest.is_file() else compare(nbformat.read(dest, as_version=4), nb)
            if state == "fresh":
                continue
            if state == "edited" and not force:
                edited.append(f"{rel} ({detail})")
                continue
            if check:
                stale.append(f"{rel} ({detail or state})")
                continue
            dest.parent.mkdir(exist_ok=True)
            dest.write_text(render(nb))
            say(f"wrote {rel}")
    if edited:
        print("edited in Jupyter, kept as it is (build.py never overwrites it): " + ", ".join(edited)
              + ". Its cells differ from its source; to work without failing this check, keep your work in a copy "
              "saved under another name (JupyterLab: File > Save Notebook As).", file=sys.stderr)
    if stale:
        print("out of date with its source, not edited since built (python notebooks/build.py rewrites it; "
              "it never overwrites a notebook edited in Jupyter): " + ", ".join(stale), file=sys.stderr)
    return 1 if edited or stale else 0


if __name__ == "__main__":
    sys.exit(main())
