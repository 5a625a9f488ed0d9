"""What a sweep runs: settings from ranges, a folder name per setting, tasks that share their first stages."""

from __future__ import annotations

import dataclasses
import hashlib
import itertools
import json
import math

from ..engine import DEPENDS, STAGES, Settings

__all__ = ["parse_values", "expand", "result_name", "plan_tasks", "plan_leaves", "LATE_FIELDS"]

#: Settings read only from the carving stage on (:data:`organlab.engine.DEPENDS`): settings that differ
#: only in these share their calibration and silhouettes, so one task runs them all through one Engine,
#: which keeps the silhouettes.  Every other field (the threshold, and fields added later) starts a new group.
LATE_FIELDS = tuple(f for stage in STAGES[STAGES.index("carving"):] for f in DEPENDS[stage])
#: Within a group, settings sharing these run one after another, so the Engine keeps the carving too.
_CARVING_FIELDS = DEPENDS["carving"]

_FLOAT_OR_AUTO = ("threshold", "color_threshold")


def _number(text, name):
    try:
        v = float(text)
    except ValueError:
        raise ValueError(f"{name}: not a number: {text!r}") from None
    if not math.isfinite(v):
        raise ValueError(f"{name}: must be finite, got {text!r}")
    return int(v) if name == "tolerance" and v == int(v) else v


def _one(text, name):
    text = text.strip()
    if name in _FLOAT_OR_AUTO and text.lower() in ("auto", "none"):
        return None
    if name in ("method", "hull"):
        return text
    if name in ("finish", "measure"):
        low = text.lower()
        if low in ("yes", "true", "1", "on"):
            return True
        if low in ("no", "false", "0", "off"):
            return False
        if name == "measure" and low in ("auto", "none"):
            return None
        raise ValueError(f"{name}: expected yes or no, got {text!r}")
    return _number(text, name)


def parse_values(text, *, name):
    """The values of one setting from its command-line form.

    ``START:STOP:STEP`` is an inclusive range (``10:40:5`` is 10, 15, ..., 40);
    ``A,B,C`` a list; ``auto`` stands for ``None`` (the automatic threshold).

    Parameters
    ----------
    text : str
    name : str
        The :class:`Settings` field (``'threshold'``, ``'voxel_size'``, ``'method'``, ...).

    Returns
    -------
    list

    Examples
    --------
    >>> parse_values("10:40:10", name="threshold")
    [10.0, 20.0, 30.0, 40.0]
    >>> parse_values("hull,coloring", name="method")
    ['hull', 'coloring']
    >>> parse_values("auto,20", name="threshold")
    [None, 20.0]
    """
    text = str(text).strip()
    if not text:
        raise ValueError(f"{name}: no value given")
    if ":" in text and name not in ("method", "hull"):
        parts = text.split(":")
        if len(parts) != 3:
            raise ValueError(f"{name}: a range is START:STOP:STEP, got {text!r}")
        start, stop, step = (_number(p, name) for p in parts)
        if step <= 0 or stop < start:
            raise ValueError(f"{name}: a range needs STEP > 0 and STOP >= START, got {text!r}")
        n = int(math.floor((stop - start) / step + 1e-9)) + 1
        if n > 10000:
            raise ValueError(f"{name}: {text!r} has {n} values; at most 10000")
        # computed from the start each time (no accumulated error), rounded to the step's decimals
        digits = max(0, -math.floor(math.log10(step)) + 6)
        return [round(start + i * step, digits) for i in range(n)]
    values = [_one(t, name) for t in text.split(",")]
    seen = []
    for v in values:
        if v not in seen:
            seen.append(v)
    return seen


def expand(grid, base=None):
    """Every combination of a grid of settings, validated.

    Parameters
    ----------
    grid : dict of str -> list
        Setting name (a :class:`Settings` field) -> its values; the first
        name varies slowest.
    base : Settings, optional
        The other settings (default ``Settings()``).

    Returns
    -------
    list of Settings

    Raises
    ------
    ValueError
        Naming the setting that is unknown or has a bad value.
    """
    base = Settings() if base is None else base
    fields = {f.name for f in dataclasses.fields(Settings)}
    if not isinstance(grid, dict) or not grid:
        raise ValueError("grid must be a non-empty dict of setting name -> list of values")
    names = list(grid)
    for name in names:
        if name not in fields:
            raise ValueError(f"grid: unknown setting {name!r}; known: {', '.join(sorted(fields))}")
        vals = grid[name]
        if isinstance(vals, (str, bytes)) or not hasattr(vals, "__iter__"):
            raise ValueError(f"grid[{name!r}] must be a list of values, got {vals!r}")
        if len(list(vals)) == 0:
            raise ValueError(f"grid[{name!r}] is empty")
    out = []
    for combo in itertools.product(*(list(grid[n]) for n in names)):
        changes = {n: _plain(v) for n, v in zip(names, combo)}
        try:
            s = base.replace(**changes).validate()
        except (TypeError, ValueError) as e:
            raise ValueError(f"grid: {e}") from None
        if s not in out:
            out.append(s)
    return out


def _plain(v):
    """numpy scalars as Python numbers (folder names and JSON stay the same whatever the caller passed)."""
    if hasattr(v, "item") and not isinstance(v, (str, bytes)):
        v = v.item()
    if isinstance(v, float) and v == int(v) and abs(v) < 1e15:
        return float(v)
    return v


def _fmt(v):
    if v is None:
        return "auto"
    if isinstance(v, bool):
        return "yes" if v else "no"
    if isinstance(v, float):
        return format(v, "g") if float(format(v, "g")) == v else repr(v)
    if isinstance(v, (int, str)):
        return str(v)
    return hashlib.sha256(json.dumps(v, default=list).encode()).hexdigest()[:8]


def result_name(settings):
    """The folder name of one setting's result: its voxel size, threshold, method and every other non-default field.

    Depends on the settings alone (not on what else a sweep varies), so a later
    sweep recognises the results of an earlier one.

    Examples
    --------
    >>> result_name(Settings(voxel_size=2.0, threshold=15.0))
    'voxel-2_threshold-15_hull'
    >>> result_name(Settings(voxel_size=0.5, method="coloring", color_threshold=8.0, finish=False))
    'voxel-0.5_threshold-auto_coloring_color_threshold-8_finish-no'
    """
    d = settings.to_dict()
    default = Settings().to_dict()
    parts = [f"voxel-{_fmt(d['voxel_size'])}", f"threshold-{_fmt(d['threshold'])}", str(d["method"])]
    for name, value in d.items():
        if name in ("voxel_size", "threshold", "method") or value == default.get(name):
            continue
        parts.append(f"{name}-{_fmt(value)}")
    return "_".join(parts)


def _cost(s):
    """A task's relative cost: the surface work grows as 1/voxel_size**2; colouring roughly doubles it."""
    return (1.0 / s.voxel_size) ** 2 * (2.0 if s.method != "hull" else 1.0)


def plan_tasks(settings, *, n_workers=1):
    """Group settings into tasks that share their calibration and silhouettes.

    Settings that differ only in :data:`LATE_FIELDS` form one group, ordered so
    that those sharing a carving run one after another.  With fewer groups
    than workers, the largest groups are split (each part recomputes the
    silhouettes, a small cost next to a worker left idle).

    Parameters
    ----------
    settings : list of Settings
    n_workers : int
        Workers that will run the tasks (0 or 1: no splitting).

    Returns
    -------
    list of list of Settings
        Tasks, the most expensive first.
    """
    groups = {}
    for s in settings:
        d = s.to_dict()
        key = json.dumps({k: v for k, v in d.items() if k not in LATE_FIELDS}, sort_keys=True, default=list)
        groups.setdefault(key, []).append(s)
    method_order = {"hull": 0}

    def order(s):
        d = s.to_dict()
        return (tuple(json.dumps(d[k], default=list) for k in _CARVING_FIELDS if k in d),
                method_order.get(d["method"], 1), json.dumps(d, sort_keys=True, default=list))

    tasks = [sorted(g, key=order) for g in groups.values()]
    while tasks and len(tasks) < n_workers:
        big = max(range(len(tasks)), key=lambda i: (len(tasks[i]) > 1, sum(map(_cost, tasks[i]))))
        g = tasks[big]
        if len(g) < 2:
            break
        # split at the carving boundary nearest to half the cost (a carving's settings stay together when they can)
        total, acc, cut = sum(map(_cost, g)), 0.0, 1
        best = None
        for i in range(1, len(g)):
            acc += _cost(g[i - 1])
            same_carving = order(g[i])[0] == order(g[i - 1])[0]
            score = (abs(acc - total / 2) / total) + (0.25 if same_carving else 0.0)
            if best is None or score < best:
                best, cut = score, i
        tasks[big:big + 1] = [g[:cut], g[cut:]]
    tasks.sort(key=lambda g: -sum(map(_cost, g)))
    return tasks


def _carving_key(s):
    d = s.to_dict()
    return tuple(json.dumps(d[k], default=list) for k in _CARVING_FIELDS if k in d)


def plan_leaves(groups: list[list[Settings]], *,
                n_workers: int = 1) -> list[tuple[str | None, list[list[Settings]]]]:
    """Split each group of :func:`plan_tasks` into the tasks that go on from its shared first stages.

    A group of several carvings (voxel sizes, tolerances) shares its
    calibration, silhouettes and poses, and has one task per carving (its
    settings run one after another through one Engine, which keeps the
    carving; one task per setting when there are fewer tasks than workers).
    A group of one carving shares the carving too, and has one task per
    setting.  The shared stages are computed once, by a task of their own
    (:func:`organlab.batch._task.run_prefix`), which the others wait for:
    their cost is not known before (the pose fit runs at some thresholds
    only), so no worker holds a whole group while another idles.

    Parameters
    ----------
    groups : list of list of Settings
        :func:`plan_tasks`'s tasks (settings that share their silhouettes, in order).
    n_workers : int

    Returns
    -------
    list of (str, list of list of Settings)
        Per group: the last stage its tasks share (``'poses'`` or
        ``'carving'``; None for a group of one setting) and its tasks, in the
        group's order.

    Examples
    --------
    >>> s = expand({"threshold": [10.0, 20.0], "method": ["hull", "coloring"], "tolerance": [0, 1]})
    >>> [(until, [len(t) for t in tasks]) for until, tasks in plan_leaves(plan_tasks(s), n_workers=2)]
    [('poses', [2, 2]), ('poses', [2, 2])]
    >>> plan_leaves(plan_tasks(expand({"method": ["hull", "coloring"]})))[0][0]
    'carving'
    """
    out = []
    for g in groups:
        carvings = []
        for s in g:
            if carvings and _carving_key(carvings[-1][-1]) == _carving_key(s):
                carvings[-1].append(s)
            else:
                carvings.append([s])
        if len(g) == 1:
            out.append([None, carvings])
        elif len(carvings) == 1:
            out.append(["carving", [[s] for s in g]])
        else:
            out.append(["poses", carvings])
    if sum(len(tasks) for _, tasks in out) < n_workers:
        out = [[until, [[s] for t in tasks for s in t]] for until, tasks in out]
    return [tuple(x) for x in out]
