"""The field-health report of a campaign: a static HTML page per campaign and per heliostat.

:func:`write_report` reads a store and writes ``OUT/``:

* ``index.html`` -- the campaign's counts (frames by stage, pairs selected,
  skip reasons counted), the **field map** (each heliostat at its pivot,
  coloured by its canting RMS, grey when not measured), the **worst
  heliostats** (highest canting RMS) with links, and the **change since
  another campaign of the same field** (map of the RMS difference and the
  heliostats that changed most, with the per-facet RMS change);
* ``heliostats/NAME.html`` + ``NAME.png`` -- per heliostat with a used facet, the
  paper's Fig. 8-style facet maps of the azimuth and elevation deviations
  (:func:`pihim.inspection.canting_output.canting_figure`) and the facet table with its
  provenance (frames, pihim version);
* ``field.png``, ``change.png``, ``report.json`` (``pihim.campaign-report/1``).

The canting RMS of a heliostat is ``sqrt(mean(az^2 + el^2) / 2)`` over its
used facets (a heliostat counts as measured with at least two: one facet is
its own reference) (:func:`pihim.campaign.run.canting_rms_mrad`), in mrad, relative
to its best-fit orientation. All files are written under temporary names and
renamed together at the end (figures are drawn and saved one at a time, so memory does not grow
with the field).
"""

from __future__ import annotations

import html
import json
import math
import os
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from pihim.errors import PihimInputError

__all__ = ["REPORT_SCHEMA_ID", "write_report"]

REPORT_SCHEMA_ID = "pihim.campaign-report/1"
_WORST = 15

_CSS = """
body{font-family:system-ui,-apple-system,Segoe UI,Roboto,sans-serif;margin:24px auto;max-width:1200px;color:#222}
h1{font-size:1.6em;margin-bottom:.2em} h2{margin-top:1.6em;border-bottom:1px solid #ccc;padding-bottom:.2em}
table{border-collapse:collapse;margin:.6em 0} td,th{border:1px solid #ccc;padding:3px 8px;text-align:right}
th{background:#f3f3f3} td.l,th.l{text-align:left} .muted{color:#666;font-size:.9em}
img{max-width:100%;border:1px solid #ddd} .grid{display:grid;grid-template-columns:1fr 1fr;gap:16px}
.bad{color:#b00} .ok{color:#070}
"""


def _page(title: str, body: str) -> str:
    return (f"<!DOCTYPE html>\n<html lang=\"en\"><head><meta charset=\"utf-8\"><title>{html.escape(title)}</title>"
            f"<style>{_CSS}</style></head><body>\n{body}\n</body></html>\n")


def _fmt(v: Any, digits: int = 2) -> str:
    if v is None or (isinstance(v, float) and not math.isfinite(v)):
        return "&ndash;"
    return f"{v:.{digits}f}" if isinstance(v, float) else html.escape(str(v))


def _pick(store: Any, campaign: str | None, compare: str | None) -> tuple[Any, Any]:
    camps = store.campaigns()
    if not camps:
        raise PihimInputError(f"{store.path}: the store has no campaign yet (run pihim campaign run first)")
    by_name = {r["name"]: r for r in camps}
    if campaign is not None and campaign not in by_name:
        raise PihimInputError(f"{store.path}: no campaign {campaign!r} (have {', '.join(by_name)})")
    cur = by_name[campaign] if campaign else camps[-1]
    prev = None
    if compare is not None:
        if compare not in by_name:
            raise PihimInputError(f"{store.path}: no campaign {compare!r} to compare with")
        prev = by_name[compare]
        if prev["field_key"] != cur["field_key"]:
            raise PihimInputError(f"campaigns {cur['name']!r} and {compare!r} are of different fields")
        if prev["id"] == cur["id"]:
            raise PihimInputError("--compare names the reported campaign itself")
    else:
        same = [r for r in camps if r["field_key"] == cur["field_key"] and r["id"] < cur["id"]]
        prev = same[-1] if same else None
    return cur, prev


def _heliostats(store: Any, cid: int) -> list[dict[str, Any]]:
    rows = store.db.execute("SELECT * FROM heliostat WHERE campaign_id = ? ORDER BY name", (cid,)).fetchall()
    return [dict(r) for r in rows]


def _facets(store: Any, heliostat_id: int) -> list[dict[str, Any]]:
    rows = store.db.execute("SELECT * FROM facet_result WHERE heliostat_id = ? ORDER BY facet",
                            (heliostat_id,)).fetchall()
    return [dict(r) for r in rows]


def _grid(n: int) -> tuple[int, int]:
    r = int(round(math.sqrt(n)))
    return (r, r) if r * r == n else (1, n)


def _field_map(ax: Any, hel: Sequence[Mapping[str, Any]], values: Mapping[str, float], *, cmap: str, label: str,
               norm: Any) -> None:
    x = np.array([h["x_m"] for h in hel])
    y = np.array([h["y_m"] for h in hel])
    v = np.array([values.get(h["name"], np.nan) for h in hel], float)
    have = np.isfinite(v)
    ax.scatter(x[~have], y[~have], s=22, marker="s", c="0.85", edgecolors="0.6", linewidths=0.5,
               label="not measured")
    sc = ax.scatter(x[have], y[have], s=34, marker="s", c=v[have], cmap=cmap, norm=norm, edgecolors="k",
                    linewidths=0.5)
    ax.plot([0], [0], marker="^", color="k", ms=9, ls="none", label="tower")
    ax.set_aspect("equal")
    ax.set_xlabel("East (m)")
    ax.set_ylabel("North (m)")
    ax.grid(alpha=0.3)
    ax.legend(loc="lower left", fontsize=8)
    ax.figure.colorbar(sc, ax=ax, label=label, shrink=0.8)


def _save(fig: Any, path: Path) -> None:
    import matplotlib.pyplot as plt

    try:
        fig.savefig(path, format="png", dpi=100)
    finally:
        plt.close(fig)


def write_report(store: Any, out_dir: str | Path, *, campaign: str | None = None,
                 compare: str | None = None) -> dict[str, Any]:
    """Write the HTML field-health report (module notes); returns the ``pihim.campaign-report/1`` summary."""
    import matplotlib

    matplotlib.use("Agg", force=False)
    import matplotlib.pyplot as plt
    from matplotlib.colors import Normalize, TwoSlopeNorm

    from pihim._atomic import atomic_group, make_out_dir
    from pihim.inspection.canting_output import canting_figure, reason_code

    cur, prev = _pick(store, campaign, compare)
    cid = int(cur["id"])
    hel = _heliostats(store, cid)
    measured = [h for h in hel if h["facets_used"]]  # pages for every heliostat with a used facet
    rms = {h["name"]: float(h["canting_rms_mrad"]) for h in measured if h["canting_rms_mrad"] is not None}
    counts = store.counts(cid)
    out = make_out_dir(Path(out_dir), option="out_dir")
    files: dict[str, Path] = {"index": out / "index.html", "json": out / "report.json", "field": out / "field.png"}
    staged: list[tuple[Path, Path]] = []  # (temporary, final): figures saved as soon as drawn, renamed at the end
    texts: dict[Path, str] = {}

    def stage(fig: Any, final: Path) -> None:
        from pihim._atomic import output_target, temp_sibling

        final = output_target(final)
        final.parent.mkdir(parents=True, exist_ok=True)
        made: list[Path] = []
        try:
            temp_sibling(final, made)
            _save(fig, made[0])
        except BaseException:
            for t in made:
                t.unlink(missing_ok=True)
            raise
        staged.append((made[0], final))

    vmax = max([1.0, *rms.values()])
    fig, ax = plt.subplots(figsize=(10.5, 7.0), constrained_layout=True)
    _field_map(ax, hel, rms, cmap="viridis", label="canting RMS (mrad)", norm=Normalize(0.0, vmax))
    ax.set_title(f"Canting RMS per heliostat, campaign {cur['name']} ({len(rms)} of {len(hel)} measured)")
    stage(fig, files["field"])

    worst = sorted(rms.items(), key=lambda kv: -kv[1])[:_WORST]
    hel_by_name = {h["name"]: h for h in hel}

    # --- change between campaigns
    change_rows: list[dict[str, Any]] = []
    if prev is not None:
        prev_hel = {h["name"]: h for h in _heliostats(store, int(prev["id"]))}
        for name, v in rms.items():
            p = prev_hel.get(name)
            if p is None or p["canting_rms_mrad"] is None:
                continue
            f_now = {f["facet"]: f for f in _facets(store, hel_by_name[name]["id"]) if f["used"]}
            f_then = {f["facet"]: f for f in _facets(store, p["id"]) if f["used"]}
            common = sorted(set(f_now) & set(f_then))
            d = [(f_now[k]["az_mrad"] - f_then[k]["az_mrad"], f_now[k]["el_mrad"] - f_then[k]["el_mrad"])
                 for k in common]
            facet_change = float(np.sqrt(np.mean(np.square(d)))) if d else None
            change_rows.append({"name": name, "rms_then": float(p["canting_rms_mrad"]), "rms_now": v,
                                "delta": v - float(p["canting_rms_mrad"]), "facets_compared": len(common),
                                "facet_change_rms_mrad": facet_change})
        change_rows.sort(key=lambda r: -abs(r["delta"]))
        if change_rows:
            files["change"] = out / "change.png"
            lim = max(0.5, max(abs(r["delta"]) for r in change_rows))
            fig, ax = plt.subplots(figsize=(10.5, 7.0), constrained_layout=True)
            _field_map(ax, hel, {r["name"]: r["delta"] for r in change_rows}, cmap="RdBu_r",
                       label="change of canting RMS (mrad)", norm=TwoSlopeNorm(0.0, -lim, lim))
            ax.set_title(f"Change of canting RMS, {prev['name']} -> {cur['name']} "
                         f"({len(change_rows)} heliostats measured in both)")
            stage(fig, files["change"])

    # --- per-heliostat pages
    for h in measured:
        facets = _facets(store, h["id"])
        rows, cols = _grid(len(facets))
        obs = store.db.execute(
            "SELECT DISTINCT target FROM observation JOIN frame ON frame.id = observation.frame_id JOIN flight ON "
            "flight.id = frame.flight_id WHERE flight.campaign_id = ? AND observation.hua = ? AND status = 'done'",
            (cid, h["name"])).fetchall()
        record = {
            "hua": h["name"], "target": "+".join(sorted(r[0] for r in obs)) or "?", "frames": h["frames"] or 0,
            "facets_used": h["facets_used"], "orientation_mrad": None,
            "facet_grid": {"rows": rows, "cols": cols},
            "facets": [{"id": f["facet"], "used": bool(f["used"]), "reason": f["reason"], "az_mrad": f["az_mrad"],
                        "el_mrad": f["el_mrad"], "az_sigma_mrad": f["az_sigma_mrad"],
                        "el_sigma_mrad": f["el_sigma_mrad"]} for f in facets],
        }
        png = out / "heliostats" / f"{h['name']}.png"
        page = out / "heliostats" / f"{h['name']}.html"
        stage(canting_figure(record), png)
        frames = json.loads(facets[0]["frame_ids"]) if facets else []
        trs = "".join(
            f"<tr><td>{f['facet']}</td><td>{'yes' if f['used'] else 'no'}</td><td>{_fmt(f['az_mrad'])}</td>"
            f"<td>{_fmt(f['el_mrad'])}</td><td>{_fmt(f['az_sigma_mrad'], 3)}</td><td>{_fmt(f['el_sigma_mrad'], 3)}</td>"
            f"<td>{f['points'] or 0}</td><td class=l>{html.escape(reason_code(f['reason']) or '')}"
            f" {html.escape(f['reason'] or '')}</td></tr>" for f in facets)
        prov = facets[0] if facets else {}
        texts[page] = _page(f"{h['name']} canting", f"""
<p><a href="../index.html">&larr; field report</a></p>
<h1>Heliostat {html.escape(h['name'])}</h1>
<p>Campaign {html.escape(cur['name'])}; canting RMS <b>{_fmt(h['canting_rms_mrad'])} mrad</b> over
{h['facets_used']} of {h['facets_total']} facets, combined from {h['frames']} frame(s).</p>
<img src="{html.escape(png.name)}" alt="facet canting maps of {html.escape(h['name'])}">
<h2>Facets</h2>
<table><tr><th>facet</th><th>used</th><th>az (mrad)</th><th>el (mrad)</th><th>&sigma; az</th><th>&sigma; el</th>
<th>points</th><th class=l>reason</th></tr>{trs}</table>
<h2>Provenance</h2>
<p class=muted>pihim {html.escape(str(prov.get('pihim_version', '')))}, computed {html.escape(str(prov.get('computed_utc', '')))};
frames: {html.escape(', '.join(frames))}<br>parameters: <code>{html.escape(str(prov.get('parameters', '')))}</code></p>
""")
        files[f"heliostat:{h['name']}"] = page

    # --- index
    fr = counts["frames"]
    skip_rows = "".join(f"<tr><td class=l>{html.escape(str(k))}</td><td>{v}</td></tr>"
                        for k, v in counts["pairs_skipped_by_reason"].items()) or "<tr><td class=l>none</td><td>0</td></tr>"
    frame_skip = "".join(f"<tr><td class=l>{html.escape(str(k))}</td><td>{v}</td></tr>"
                         for k, v in counts["frames_skipped_by_reason"].items()) or "<tr><td class=l>none</td><td>0</td></tr>"
    worst_rows = "".join(
        f"<tr><td class=l><a href=\"heliostats/{html.escape(n)}.html\">{html.escape(n)}</a></td><td>{v:.2f}</td>"
        f"<td>{hel_by_name[n]['facets_used']}/{hel_by_name[n]['facets_total']}</td><td>{hel_by_name[n]['frames']}</td></tr>"
        for n, v in worst) or "<tr><td class=l colspan=4>no heliostat measured yet</td></tr>"
    if prev is None:
        change_html = "<p>No earlier campaign of this field in the store.</p>"
    elif not change_rows:
        change_html = f"<p>No heliostat measured in both {html.escape(prev['name'])} and {html.escape(cur['name'])}.</p>"
    else:
        crow = "".join(
            f"<tr><td class=l><a href=\"heliostats/{html.escape(r['name'])}.html\">{html.escape(r['name'])}</a></td>"
            f"<td>{r['rms_then']:.2f}</td><td>{r['rms_now']:.2f}</td>"
            f"<td class={'bad' if r['delta'] > 0 else 'ok'}>{r['delta']:+.2f}</td>"
            f"<td>{_fmt(r['facet_change_rms_mrad'])}</td><td>{r['facets_compared']}</td></tr>"
            for r in change_rows[:_WORST])
        change_html = f"""<p>Since campaign <b>{html.escape(prev['name'])}</b>: {len(change_rows)} heliostats measured
in both; largest changes first. The facet change is the RMS over common facets of the difference of their
deviations (mrad).</p>
<img src="change.png" alt="map of the change of canting RMS">
<table><tr><th class=l>heliostat</th><th>RMS then</th><th>RMS now</th><th>change</th><th>facet change RMS</th>
<th>facets compared</th></tr>{crow}</table>"""
    texts[files["index"]] = _page(f"pihim field health: {cur['name']}", f"""
<h1>Field health: campaign {html.escape(cur['name'])}</h1>
<p class=muted>Store {html.escape(str(store.path))}; field {html.escape(cur['field_source'])};
created {html.escape(cur['created_utc'])}. Canting RMS = sqrt(mean(az&sup2; + el&sup2;)/2) over a heliostat's
used facets, relative to its best-fit orientation.</p>
<table><tr><th class=l>frames</th><th>done</th><th>selected</th><th>skipped</th><th>pending</th></tr>
<tr><td class=l>count</td><td>{fr['done']}</td><td>{fr['selected']}</td><td>{fr['skipped']}</td><td>{fr['pending']}</td></tr></table>
<p>HUA-target pairs: {counts['pairs']['candidates']} seen, {counts['pairs']['selected']} passed the selection,
{counts['pairs']['chosen']} chosen for canting; observations {counts['observations']['done']} done,
{counts['observations']['failed']} failed; <b>{len(rms)} heliostats measured</b> of {len(hel)}.</p>
<div class=grid><div><h3>Pairs skipped, by reason</h3><table><tr><th class=l>reason</th><th>pairs</th></tr>{skip_rows}</table></div>
<div><h3>Frames skipped, by reason</h3><table><tr><th class=l>reason</th><th>frames</th></tr>{frame_skip}</table></div></div>
<h2>Field map</h2>
<img src="field.png" alt="field map coloured by canting RMS">
<h2>Worst heliostats</h2>
<table><tr><th class=l>heliostat</th><th>canting RMS (mrad)</th><th>facets used</th><th>frames</th></tr>{worst_rows}</table>
<h2>Change between campaigns</h2>
{change_html}
""")
    summary = {
        "schema": REPORT_SCHEMA_ID,
        "campaign": cur["name"],
        "compared_with": None if prev is None else prev["name"],
        "heliostats": len(hel),
        "heliostats_measured": len(rms),
        "worst": [{"name": n, "canting_rms_mrad": round(v, 4)} for n, v in worst],
        "changes": [{k: (round(v, 4) if isinstance(v, float) else v) for k, v in r.items()} for r in change_rows],
        "counts": counts,
        "files": {k: str(v) for k, v in files.items()},
    }
    texts[files["json"]] = json.dumps(summary, indent=2, allow_nan=False) + "\n"
    (out / "heliostats").mkdir(exist_ok=True)
    targets = list(texts)
    try:
        with atomic_group(targets) as tmps:
            for final, tmp in zip(targets, tmps, strict=True):
                tmp.write_text(texts[final], encoding="utf-8")
            for tmp, final in staged:
                os.replace(tmp, final)
    except BaseException:
        for tmp, _ in staged:
            tmp.unlink(missing_ok=True)
        raise
    return summary
