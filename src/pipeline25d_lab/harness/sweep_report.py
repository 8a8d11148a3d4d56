"""Sweep results: Pareto fronts of wall time against error, written as JSON, a plot and a table.

Each objective pairs wall time with one error (both minimized): check-point RMSD and the
LOD error drawn, both in metres (pixels are not comparable across gsd variants), and
the map error against a reference render. Fronts are taken over all variants, and per
factor over the defaults plus that factor's variants, which says whether the default of
that factor is a Pareto-optimal choice. A run is faster than another only by more than the
noise band (the spread of the defaults' repeated runs). A failed variant (``error`` in its
row) has no figures and is on no front.
"""

from __future__ import annotations

import math
from pathlib import Path

from pipeline25d.core.atomic import atomic_path, write_json
from pipeline25d_lab.harness.pareto import pareto_front

OBJECTIVES = {"rmsd_m": "check-point RMSD, m (mean of the oblique views)",
              "lod_m": "LOD error drawn, m (largest over rendered chunks; px at the run's gsd)",
              "map_mad": "map error, grey levels (mean abs. difference from most MSAA, finest LOD)"}
FIGSIZE, DPI = (18.0, 5.5), 100          # the PNG is 1800 x 550 px
LABEL_PT, LABEL_CHAR_PT, LABEL_LINE_PT = 8, 4.8, 10   # label font size, rough width of a character, line step
LOG_SPAN = 20                            # an error axis spanning more than this ratio is logarithmic


def _num(value: float | None) -> float:
    return math.nan if value is None else float(value)


def _points(rows: list[dict], objective: str) -> list[tuple[float, float]]:
    return [(_num(r.get("wall_s")), _num(r.get(objective))) for r in rows]


def wall_noise(rows: list[dict]) -> float:
    """The noise band of wall time: the spread of the defaults' repeated runs (0 without repeats)."""
    runs = next((r.get("wall_runs") or [] for r in rows if r["factor"] == "default"), [])
    return round(max(runs) - min(runs), 1) if len(runs) > 1 else 0.0


def summarize(rows: list[dict], meta: dict) -> dict:
    """``meta`` plus the rows (each with ``on_front`` per objective), the fronts by variant name,
    whether the defaults are on them, and the same per factor; wall times differing by no more
    than :func:`wall_noise` count as equal."""
    rows = [dict(r) for r in rows]
    for r in rows:                   # the LOD error in metres: a pixel of a gsd variant is another size
        if r.get("lod_px") is not None and r.get("gsd") is not None:
            r["lod_m"] = round(r["lod_px"] * r["gsd"], 4)
    default = next((i for i, r in enumerate(rows) if r["factor"] == "default"), None)
    noise = wall_noise(rows)
    tolerance = (noise, 0.0)
    front, default_on = {}, {}
    for obj in OBJECTIVES:
        idx = pareto_front(_points(rows, obj), tolerance)
        front[obj] = [rows[i]["name"] for i in idx]
        default_on[obj] = default in idx
        for i, r in enumerate(rows):
            r.setdefault("on_front", {})[obj] = i in idx
    factors = {}
    for factor in dict.fromkeys(r["factor"] for r in rows if r["factor"] != "default"):
        members = [i for i, r in enumerate(rows) if r["factor"] == factor or i == default]
        entry: dict = {"variants": [rows[i]["name"] for i in members], "front": {}, "default_on_front": {}}
        for obj in OBJECTIVES:
            points = _points(rows, obj)
            idx = [members[j] for j in pareto_front([points[i] for i in members], tolerance)]
            entry["front"][obj] = [rows[i]["name"] for i in idx]
            entry["default_on_front"][obj] = default in idx
        factors[factor] = entry
    return {**meta, "objectives": OBJECTIVES, "wall_noise_s": noise, "front": front, "default_on_front": default_on,
            "factors": factors, "variants": rows}


def plot_sweep(summary: dict, path: str | Path) -> None:
    """One panel per objective, wall time against its error: every variant labelled, the defaults a star,
    the Pareto front a step line through ringed points."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    rows = [r for r in summary["variants"] if "error" not in r]
    factors = list(dict.fromkeys(r["factor"] for r in rows if r["factor"] != "default"))
    fig = Figure(figsize=FIGSIZE, dpi=DPI, layout="constrained")
    FigureCanvasAgg(fig)
    axes = fig.subplots(1, len(OBJECTIVES), sharey=True)
    axes[0].set_ylabel("wall time of the whole run, s")
    for ax, obj in zip(axes, OBJECTIVES):
        _panel(ax, rows, obj, factors, legend=ax is axes[0])
    axes[0].set_ylim(0, 1.08 * max((r["wall_s"] for r in rows), default=1.0))
    colours = {"default": "black"} | {f: f"C{k}" for k, f in enumerate(factors)}
    for ax, obj in zip(axes, OBJECTIVES):        # once both panels' limits are final
        _label(ax, [(r[obj], r["wall_s"], _label_text(r, obj), colours[r["factor"]])
                    for r in rows if math.isfinite(_num(r.get(obj)))])
    fig.legend(loc="outside lower center", ncols=len(factors) + 2, fontsize=9, frameon=False)
    failed = len(summary["variants"]) - len(rows)
    fig.suptitle(f"{summary.get('name', 'sweep')}: {summary.get('scene', '')}, {len(rows)} variants on "
                 f"{summary.get('cores', '?')} cores" + (f" ({failed} failed, not shown)" if failed else "")
                 + f", lower left is better; wall-time noise band {summary.get('wall_noise_s', 0)} s")
    with atomic_path(path) as tmp:
        fig.savefig(tmp, format="png")


def _panel(ax, rows: list[dict], obj: str, factors: list[str], legend: bool) -> None:
    """Wall time against ``obj``: points by factor, the defaults a star, the front a step line."""
    from matplotlib.ticker import FuncFormatter

    shown = [r for r in rows if math.isfinite(_num(r.get(obj)))]
    for k, factor in enumerate(["default", *factors]):
        sel = [r for r in shown if r["factor"] == factor]
        style = {"marker": "*", "s": 260, "color": "black", "zorder": 4} if factor == "default" else \
            {"marker": "o", "s": 40, "color": f"C{k - 1}", "zorder": 3}     # C0, C1, ... by factor
        ax.scatter([r[obj] for r in sel], [r["wall_s"] for r in sel], label=factor if legend else None, **style)
    front = sorted((r[obj], r["wall_s"]) for r in shown if r["on_front"][obj])
    ax.plot([x for x, _ in front], [y for _, y in front], drawstyle="steps-post", color="0.4", lw=1.5, zorder=2,
            label="Pareto front" if legend else None)
    ax.scatter([x for x, _ in front], [y for _, y in front], s=150, facecolors="none", edgecolors="0.4", zorder=2)
    ax.set_xlabel(OBJECTIVES[obj])
    ax.grid(alpha=0.3)
    values = [r[obj] for r in shown] or [1.0]
    lo, hi = min(values), max(values)
    if lo > 0 and hi / lo > LOG_SPAN:           # a few far-off runs would squash the rest into one column
        ax.set_xscale("log")
        ax.set_xlim(lo / 1.5, hi * 2.5)
        ax.xaxis.set_major_formatter(FuncFormatter(lambda v, _: f"{v:g}"))
        ax.xaxis.set_minor_formatter(FuncFormatter(lambda v, _: f"{v:g}" if f"{v:.0e}"[0] in "25" else ""))
    else:
        right = 1.25 * hi or 1.0
        ax.set_xlim(-0.02 * right, right)                   # points at 0 whole, not cut by the axis
    if hi == 0 and obj == "lod_m":
        ax.text(0.5, 0.5, "every run drew full-detail levels only (error 0)", transform=ax.transAxes,
                ha="center", color="0.4")


def _label_text(row: dict, obj: str) -> str:
    """The variant's name; with its error in pixels where the gsd may differ from the defaults'."""
    px = {"rmsd_m": row.get("rmsd_px"), "lod_m": row.get("lod_px")}.get(obj)
    if row["factor"] in ("default", "gsd") and px is not None:
        return f"{row['name']} ({px:.2f} px)"
    return row["name"]


def _label(ax, items: list[tuple[float, float, str, str]]) -> None:
    """Annotate each (x, y, text, colour) right or left of its point, whichever needs the smaller
    nudge upward to clear the labels already placed (a nudged label gets a leader line)."""
    to_pt = 72 / ax.figure.dpi
    placed: list[tuple[float, float, float]] = []           # (left, right, baseline) in points
    for x, y, text, colour in sorted(items, key=lambda t: (t[1], t[0])):
        px, py = (v * to_pt for v in ax.transData.transform((x, y)))
        width = LABEL_CHAR_PT * len(text)
        best = None
        for side in (1, -1):
            left = px + 8 if side > 0 else px - 8 - width
            dy = 3.0
            while any(abs(py + dy - b) < LABEL_LINE_PT and left < x1 and left + width > x0 for x0, x1, b in placed):
                dy += LABEL_LINE_PT / 2
            if best is None or dy < best[0]:
                best = (dy, side, left)
        dy, side, left = best
        placed.append((left, left + width, py + dy))
        ax.annotate(text, (x, y), xytext=(8 * side, dy), textcoords="offset points", fontsize=LABEL_PT,
                    color=colour, ha="left" if side > 0 else "right",
                    arrowprops={"arrowstyle": "-", "color": colour, "lw": 0.6} if dy > LABEL_LINE_PT else None)


def write_sweep(summary: dict, out_json: str | Path, out_png: str | Path) -> None:
    """The summary as JSON and its plot as PNG, each written atomically."""
    write_json(out_json, summary)
    plot_sweep(summary, out_png)


def _fmt(value: float | None, nd: int) -> str:
    return "n/a" if value is None else f"{value:.{nd}f}"


def format_table(summary: dict) -> str:
    """A plain-text table of the variants and which fronts hold them, then the defaults' verdicts."""
    lines = [f"{'variant':<12} {'wall s':>7} {'job s':>7} {'RMSD px':>8} {'RMSD m':>7} {'LOD px':>7} {'map MAD':>8}"
             f" {'tiles':>6} {'load':>5}  on front"]
    for r in summary["variants"]:
        if "error" in r:
            lines.append(f"{r['name']:<12} failed: {r['error']}")
            continue
        on = ", ".join(obj for obj in OBJECTIVES if r["on_front"][obj]) or "-"
        load = _fmt(sum(r["load_avg"]) / 2, 1) if r.get("load_avg") else "-"
        lines.append(f"{r['name']:<12} {r['wall_s']:>7.1f} {r['job_s']:>7.1f} {_fmt(r['rmsd_px'], 3):>8} "
                     f"{_fmt(r['rmsd_m'], 3):>7} {_fmt(r['lod_px'], 3):>7} {_fmt(r.get('map_mad'), 2):>8} "
                     f"{r['tiles_rendered']:>6} {load:>5}  {on}")

    def verdict(flags: dict) -> str:
        return ", ".join(f"{obj} {'yes' if flags[obj] else 'no'}" for obj in OBJECTIVES)

    lines += ["", f"wall-time noise band (spread of the defaults' runs): {summary.get('wall_noise_s', 0)} s",
              f"defaults on the front of all runs: {verdict(summary['default_on_front'])}"]
    lines += [f"  within {factor}: {verdict(f['default_on_front'])}" for factor, f in summary["factors"].items()]
    return "\n".join(lines)
