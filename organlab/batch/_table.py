"""The answer a tuner wants: one row per result, the recommended setting and why, plots."""

from __future__ import annotations

import math

import numpy as np

__all__ = ["row_of", "SETTING_COLUMNS", "recommend", "plot_sweep"]

#: The settings shown in the table, in this order (other fields follow when present).
SETTING_COLUMNS = ("voxel_size", "threshold", "method", "hull", "color_threshold", "tolerance", "finish", "measure")

_NAN = float("nan")


def row_of(session_name, name, entry):
    """One table row from a task's entry (:func:`organlab.batch._task.run_task`) or a finished folder's report.

    Columns: ``session``, ``name`` (the result's folder), ``status``
    (``'done'``, ``'finished before'``, ``'error'``), the settings, then
    ``volume_mm3`` (the carved voxels), ``mesh_volume_mm3``,
    ``volume_error_pct`` / ``mesh_volume_error_pct`` (against the session's
    reference, NaN without one), ``agreement_mean_iou`` and
    ``agreement_worst_iou`` (model outline against the silhouettes, over the
    views), ``worst_view``, ``n_warnings``, ``warnings``, ``watertight``,
    ``faces``, ``min_angle_deg``, ``faces_below_20deg`` (the finished surface),
    ``seconds`` (this setting's wall time), ``cpu_seconds`` (the CPU time
    of the process that ran it meanwhile), ``stages_run`` (the stages
    computed for it, the others kept from the setting before it in its task;
    empty for a result finished before) and ``time_<stage>_s`` (the time
    each stage took where it ran), ``error``.
    """
    settings = entry["settings"]
    row = {"session": session_name, "name": name, "status": entry.get("status", "done")}
    for k in SETTING_COLUMNS:
        row[k] = settings.get(k)
    for k, v in settings.items():
        if k not in row and k != "roi":
            row[k] = v
    rep = entry.get("report")
    if entry.get("error") or rep is None:
        row.update(status="error", error=entry.get("error") or "no report")
        return row
    views = rep.get("views", [])
    ious = [v["agreement"]["iou"] for v in views if "agreement" in v]
    worst = int(np.argmin(ious)) if ious else None
    final = rep.get("surface", {}).get("final", {})
    warnings = list(rep.get("warnings", []))
    row.update(
        volume_mm3=float(rep["volume_mm3"]),
        mesh_volume_mm3=float(rep["mesh_volume_mm3"]),
        volume_error_pct=float(rep.get("volume_error_pct", _NAN)),
        mesh_volume_error_pct=float(rep.get("mesh_volume_error_pct", _NAN)),
        agreement_mean_iou=float(np.mean(ious)) if ious else _NAN,
        agreement_worst_iou=float(ious[worst]) if ious else _NAN,
        worst_view=views[worst]["image"] if ious else "",
        n_warnings=len(warnings),
        warnings=" | ".join(warnings),
        watertight=bool(rep.get("watertight")),
        faces=final.get("faces", _NAN),
        min_angle_deg=final.get("min_angle_deg", _NAN),
        faces_below_20deg=final.get("faces_below_20deg", _NAN),
        seconds=float(entry.get("seconds", _NAN)),
        cpu_seconds=float(entry.get("cpu_seconds", _NAN)),
        stages_run=",".join(entry.get("stages_run", ())),
    )
    for stage, t in rep.get("timings_s", {}).items():
        row[f"time_{stage}_s"] = float(t)
    row["error"] = ""
    return row


def _is_number(v):
    return isinstance(v, (int, float)) and not isinstance(v, bool) and v is not None and math.isfinite(v)


def recommend(df, *, plateau_tol=0.01, volume="volume_mm3"):
    """The setting to use: on the widest plateau of volume against the threshold, with the best agreement.

    For each combination of the other swept settings, the thresholds are
    sorted and a *plateau* is a run of consecutive thresholds between which
    the volume changes by at most ``plateau_tol`` (relative).  The widest
    plateau (most thresholds) of each combination is kept; its thresholds at
    the ends of the swept range are dropped when it has three or more (one
    side of them is unknown).  Of the remaining results the one with the best
    mean agreement (IoU of the model's outline with the silhouettes) wins,
    then the flattest (smallest relative volume change to its neighbours).
    Without several numeric thresholds the best agreement wins alone.

    Parameters
    ----------
    df : pandas.DataFrame
        The sweep's table (results with ``status`` 'error' are ignored).
    plateau_tol : float
        Relative volume change allowed between neighbouring thresholds.
    volume : str
        The volume column.

    Returns
    -------
    dict or None
        ``name``, ``settings`` (dict of the swept columns), ``reason`` (one
        sentence), ``plateau`` (thresholds), or None without any result.
    """
    ok = df[df["status"] != "error"]
    if ok.empty:
        return None
    others = [c for c in SETTING_COLUMNS if c != "threshold" and c in ok and ok[c].astype(str).nunique() > 1]
    candidates = []  # (agreement, -flatness, row index, plateau thresholds, change)
    for _, sub in (ok.groupby(others, dropna=False, sort=False) if others else [(None, ok)]):
        numeric = sub[[_is_number(t) for t in sub["threshold"]]].sort_values("threshold")
        if len(numeric) < 2:
            for i, r in sub.iterrows():
                candidates.append((r["agreement_mean_iou"], 0.0, i, [], _NAN))
            continue
        t = numeric["threshold"].to_numpy(float)
        v = numeric[volume].to_numpy(float)
        step = np.abs(np.diff(v)) / np.maximum(np.minimum(v[:-1], v[1:]), 1e-12)  # relative change per step
        runs, start = [], 0
        for k, s in enumerate(step):
            if s > plateau_tol:
                runs.append((start, k))
                start = k + 1
        runs.append((start, len(v) - 1))
        a, b = max(runs, key=lambda r: (r[1] - r[0], -float(np.mean(step[r[0]:r[1]])) if r[1] > r[0] else 0.0))
        if b == a:  # no two neighbouring thresholds agree: no plateau in this combination
            continue
        lo, hi = a, b
        if b - a >= 2:  # the swept range's ends: the volume beyond them is unknown
            lo += int(a == 0)
            hi -= int(b == len(v) - 1)
        for k in range(lo, hi + 1):
            left = step[k - 1] if k > 0 else _NAN
            right = step[k] if k < len(step) else _NAN
            change = float(np.nanmax([left, right]))
            i = numeric.index[k]
            candidates.append((numeric.loc[i, "agreement_mean_iou"], -change, i, [float(x) for x in t[a:b + 1]], change))
    if not candidates:
        best = ok["agreement_mean_iou"].idxmax()
        r = ok.loc[best]
        return {"name": r["name"], "settings": _settings(r), "plateau": [],
                "reason": (f"no plateau: the volume changes by more than {100 * plateau_tol:g} % between every two "
                           f"neighbouring thresholds; best mean agreement (IoU {r['agreement_mean_iou']:.4f}) at "
                           f"threshold {_fmt(r['threshold'])}; sweep finer or lower thresholds")}
    agreement, _, i, plateau, change = max(candidates, key=lambda c: (c[0], c[1]))
    r = ok.loc[i]
    if plateau:
        reason = (f"threshold {_fmt(r['threshold'])} lies on the plateau {_fmt(plateau[0])}-{_fmt(plateau[-1])} where the "
                  f"volume changes by at most {100 * plateau_tol:g} % between neighbouring thresholds "
                  f"({100 * change:.2f} % next to it), and has the best mean agreement there "
                  f"(IoU {agreement:.4f}, worst view {r['agreement_worst_iou']:.4f})")
    else:
        reason = f"best mean agreement (IoU {agreement:.4f}, worst view {r['agreement_worst_iou']:.4f}); no threshold range was swept"
    others_text = ", ".join(f"{c} {_fmt(r[c])}" for c in others)
    if others_text:
        reason += f", with {others_text}"
    return {"name": r["name"], "settings": _settings(r), "plateau": plateau, "reason": reason}


def _settings(r):
    return {c: (None if (isinstance(r[c], float) and math.isnan(r[c])) else _py(r[c])) for c in SETTING_COLUMNS if c in r}


def _py(v):
    return v.item() if hasattr(v, "item") else v


def _fmt(v):
    if v is None or (isinstance(v, float) and math.isnan(v)):
        return "auto"
    if isinstance(v, float):
        return format(v, "g")
    return str(_py(v))


def plot_sweep(df, swept, folder):
    """PNG plots: volume and agreement against each swept setting, one line per combination of the others.

    Parameters
    ----------
    df : pandas.DataFrame
    swept : list of str
        The settings that take more than one value.
    folder : Path
        Created; ``volume_agreement_vs_<setting>.png`` written there.

    Returns
    -------
    list of Path
    """
    from matplotlib.figure import Figure

    folder.mkdir(parents=True, exist_ok=True)
    ok = df[df["status"] != "error"]
    paths = []
    if ok.empty:
        return paths
    for x in swept:
        others = [c for c in swept if c != x]
        fig = Figure(figsize=(10, 4), layout="constrained")
        axv, axa = fig.subplots(1, 2)
        values = list(dict.fromkeys(ok[x].tolist()))
        numeric = all(_is_number(v) for v in values)
        order = sorted(values) if numeric else values
        pos = {v if numeric else _fmt(v): (v if numeric else k) for k, v in enumerate(order)}
        groups = ok.groupby(others, dropna=False, sort=False) if others else [((), ok)]
        for key, sub in groups:
            key = key if isinstance(key, tuple) else (key,)
            label = ", ".join(f"{c} {_fmt(k)}" for c, k in zip(others, key)) or None
            sub = sub.copy()
            sub["_x"] = [pos[v if numeric else _fmt(v)] for v in sub[x]]
            sub = sub.sort_values("_x")
            axv.plot(sub["_x"], sub["volume_mm3"] / 1000.0, "o-", label=label)
            axa.plot(sub["_x"], sub["agreement_mean_iou"], "o-", label=label)
        ref = ok["volume_mm3"] / (1 + ok["volume_error_pct"] / 100.0)
        if ref.notna().any():
            axv.axhline(float(ref.dropna().iloc[0]) / 1000.0, color="grey", ls="--", lw=1, label="reference")
        for ax, what in ((axv, "volume (cm3)"), (axa, "mean agreement (IoU)")):
            ax.set_xlabel(x.replace("_", " ") + (" (mm)" if x == "voxel_size" else ""))
            ax.set_ylabel(what)
            ax.grid(True, alpha=0.3)
            if not numeric:
                ax.set_xticks(range(len(order)), [_fmt(v) for v in order])
        if axv.get_legend_handles_labels()[1]:
            axv.legend(fontsize=8)
        fig.suptitle(f"{ok['session'].iloc[0]}: volume and agreement against {x.replace('_', ' ')}")
        path = folder / f"volume_agreement_vs_{x}.png"
        fig.savefig(path, dpi=100)
        paths.append(path)
    return paths
