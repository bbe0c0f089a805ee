"""A self-contained HTML report of an inspection scored against rendered truth (``pihim demo``).

:func:`write_report` turns the ``pihim.demo/2`` document of
:func:`pihim.demo.run_demo` into one static page: no script, no server, no
network; the images are the PNG files beside it (relative links), so the
folder can be zipped, mailed or opened from disk.
"""

from __future__ import annotations

import html
from pathlib import Path
from typing import Any

__all__ = ["render_report", "write_report"]

_CSS = """
body{font-family:system-ui,-apple-system,"Segoe UI",Roboto,sans-serif;margin:1.5em auto;max-width:1300px;
     color:#1d1d1f;line-height:1.4;padding:0 1em}
h1{font-size:1.6em;margin-bottom:.2em}h2{margin-top:1.8em;border-bottom:1px solid #ccc;padding-bottom:.2em}
h3{margin-top:1.4em}
table{border-collapse:collapse;margin:.6em 0;font-size:.9em}
td,th{border:1px solid #ccc;padding:.25em .5em;text-align:right}
th{background:#f0f0f3}td.l,th.l{text-align:left}
tr.skip td{color:#888}
.grid{display:grid;grid-template-columns:repeat(3,1fr);gap:.6em}
.grid figure{margin:0}.grid img{width:100%;border:1px solid #ddd}
figcaption{font-size:.85em;color:#555}
img.wide{max-width:100%;border:1px solid #ddd}
.kpi{display:flex;gap:1em;flex-wrap:wrap}.kpi div{background:#f4f6fa;border-radius:6px;padding:.5em .9em}
.kpi b{display:block;font-size:1.3em}
.note{color:#555;font-size:.9em}
"""


def _f(v: Any, spec: str = "+.2f") -> str:
    if v is None:
        return "&ndash;"
    if isinstance(v, bool):
        return "yes" if v else "no"
    if isinstance(v, (int, float)):
        return format(v, spec)
    return html.escape(str(v))


def _track(t: Any) -> str:
    if isinstance(t, dict) and "az" in t and "el" in t:
        return f"az {_f(t['az'])}, el {_f(t['el'])} mrad"
    return "unknown"


def _img(src: str, alt: str, cls: str = "") -> str:
    c = f' class="{cls}"' if cls else ""
    return f'<img src="{html.escape(src, quote=True)}" alt="{html.escape(alt, quote=True)}"{c} loading="lazy">'


def _pair_section(p: dict[str, Any]) -> str:
    e = html.escape
    title = f"{e(p['hua'])} reflecting {e(p['target'])}"
    parts = [f"<h2>{title}</h2>"]
    d = p["dir"]
    if "error" in p:
        parts.append(f"<p><b>Not inspected:</b> {e(p['error'])}</p>")
        return "\n".join(parts)
    s = p["score"]
    pose = s["pose"]
    sec = p["seconds"]
    parts.append('<div class="kpi">'
                 f"<div>facets measured<b>{s['facets_used']} / {len(s['facets'])}</b></div>"
                 f"<div>canting RMS error az / el<b>{_f(s['rms_az_mrad'], '.2f')} / "
                 f"{_f(s['rms_el_mrad'], '.2f')} mrad</b></div>"
                 f"<div>paper grid search az / el<b>{_f(s['grid_rms_az_mrad'], '.2f')} / "
                 f"{_f(s['grid_rms_el_mrad'], '.2f')} mrad</b></div>"
                 f"<div>pose error at the facet corners<b>{_f(pose['prior_corner_error_px'], '.0f')} &rarr; "
                 f"{_f(pose['refined_corner_error_px'], '.2f')} px</b></div>"
                 f"<div>inspection time<b>{_f(sec.get('total'), '.1f')} s</b></div>"
                 "</div>")
    pv = p["previews"]
    figs = [("S0", "S0 (intensity)"), ("DoLP", "DoLP (0..1, viridis)"), ("AoP", "AoP (hue; brightness DoLP)"),
            ("edges_S0", "Canny edges of S0 (noise-weighted)"), ("edges_DoLP", "Canny edges of DoLP (noise-weighted)"),
            ("edges_AoP", "Canny edges of axial AoP (noise-weighted)")]
    parts.append('<div class="grid">' + "".join(
        f"<figure>{_img(f'{d}/{pv[k]}', cap)}<figcaption>{e(cap)}</figcaption></figure>" for k, cap in figs)
        + "</div>")
    es = s["edge_success"]
    parts.append("<p>Edge success (the paper's criterion: every visible facet edge of the HUA found, judged "
                 "against the true projected outlines): " + ", ".join(
                     f"{k} {'<b>yes</b>' if v['success'] else 'no'} ({v['edges_judged'] - v['edges_failed']}/"
                     f"{v['edges_judged']} edges)" for k, v in es.items()) + ".</p>")
    parts.append(f"<h3>Canting</h3>{_img(d + '/' + p['canting'], 'canting figure', 'wide')}")
    o = s.get("orientation")
    if o:
        parts.append("<p>Best-fit heliostat orientation (the mean raw deviation of the facets used, which the "
                     "facet values are relative to): estimated az "
                     f"{_f(o['est_az_mrad'])}, el {_f(o['est_el_mrad'])} mrad; true mean canting deviation of the "
                     f"same facets az {_f(o['true_mean_deviation_az_mrad'])}, el "
                     f"{_f(o['true_mean_deviation_el_mrad'])} mrad (true tracking error "
                     f"{_track(o['true_tracking_error_mrad'])}). The two differ by the camera pose's and "
                     "the logged drive angles' common offset, which a single frame cannot separate.</p>")
    rows = ["<tr><th>facet</th><th>est az</th><th>true az</th><th>error az</th><th>grid error az</th>"
            "<th>est el</th><th>true el</th><th>error el</th><th>grid error el</th><th>&sigma; az / el</th>"
            "<th class=l>status</th></tr>"]
    for f in s["facets"]:
        if f["used"]:
            rows.append(
                f"<tr><td>{f['id']}</td><td>{_f(f['est_az_mrad'])}</td><td>{_f(f['true_rel_az_mrad'])}</td>"
                f"<td><b>{_f(f['err_az_mrad'])}</b></td><td>{_f(f['grid_err_az_mrad'])}</td>"
                f"<td>{_f(f['est_el_mrad'])}</td><td>{_f(f['true_rel_el_mrad'])}</td>"
                f"<td><b>{_f(f['err_el_mrad'])}</b></td><td>{_f(f['grid_err_el_mrad'])}</td>"
                f"<td>{_f(f['az_sigma_mrad'], '.2g')} / {_f(f['el_sigma_mrad'], '.2g')}</td>"
                "<td class=l>used</td></tr>")
        else:
            rows.append(f"<tr class=skip><td>{f['id']}</td>" + "<td>&ndash;</td>" * 9
                        + f"<td class=l>{e(f['reason'] or '')}</td></tr>")
    parts.append("<p class=note>Facet deviations in mrad, heliostat frame, relative to the mean over the facets "
                 "used (estimate) and to the true mean over the same facets (truth); grid = the paper's "
                 "0.1&deg; (1.75 mrad) grid search on the same frame; &sigma; is the fit's standard error (a "
                 "jackknife over the target outline's segments matched in the facet), which leaves out a fit "
                 "locked onto other features and camera pose errors.</p>")
    parts.append("<table>" + "".join(rows) + "</table>")
    pf = p["pose_fit"]
    parts.append(
        "<h3>Pose and times</h3><table>"
        f"<tr><th class=l>logged pose off by</th><td>{_f(pose['prior_position_error_m'], '.2f')} m</td>"
        f"<td>{_f(pose['prior_corner_error_px'], '.0f')} px at the facet corners</td></tr>"
        f"<tr><th class=l>refined pose off by</th><td>{_f(pose['refined_position_error_m'], '.3f')} m, "
        f"{_f(pose['refined_rotation_error_deg'], '.3f')}&deg;</td>"
        f"<td>{_f(pose['refined_corner_error_px'], '.2f')} px (fit residual {_f(pf['rms_px'], '.2f')} px, "
        f"support {_f(pf['support'], '.2f')}, {pf['starts']} starts)</td></tr></table>"
        "<table><tr>" + "".join(f"<th>{e(k)}</th>" for k in sec) + "</tr><tr>"
        + "".join(f"<td>{_f(v, '.2f')} s</td>" for v in sec.values()) + "</tr></table>"
        f"<p class=note>Files: <a href=\"{e(p['frame'])}\">raw frame</a>, "
        f"<a href=\"{e(d)}/frame.json\">log and truth</a>, <a href=\"{e(d)}/{e(p['canting_json'])}\">canting.json"
        "</a>.</p>")
    return "\n".join(parts)


def render_report(doc: dict[str, Any]) -> str:
    """The HTML text of the report for a ``pihim.demo/2`` document."""
    from pihim.planning.scoring import images_text

    e = html.escape
    st = doc["settings"]
    plan = doc["plan"]
    sm = doc["summary"]
    head = (
        "<!DOCTYPE html><html lang=en><head><meta charset=utf-8>"
        "<meta name=viewport content=\"width=device-width,initial-scale=1\">"
        f"<title>pihim demo: {e(plan['time'])}</title><style>{_CSS}</style></head><body>"
    )
    intro = (
        f"<h1>pihim demo: polarimetric inspection of the NSTTF-like field, {e(plan['time'])}</h1>"
        "<p>Everything below was planned, rendered, measured and scored by <code>pihim demo</code>. The "
        "estimator reads only the raw frame and the drone's log; the rendered <i>truth</i> (true camera pose, "
        "every facet's canting) is used only to score it. "
        f"Canting drawn N(0, {st['canting_sigma_mrad']:g} mrad) per axis, logged pose off by "
        f"N(0, {st['gps_sigma_m']:g} m) GPS and N(0, {st['attitude_sigma_deg']:g}&deg;) attitude noise, "
        f"Triton {st['width_px']}&times;{st['height_px']} sensor with shot and read noise.</p>"
        '<div class="kpi">'
        f"<div>pairs inspected<b>{sm['pairs']}</b></div>"
        f"<div>poses within 2 px<b>{sm['pose_refined_within_2px']} / {sm['pairs']}</b></div>"
        f"<div>facets measured<b>{sm['facets_used']}</b></div>"
        f"<div>canting RMS error az / el<b>{_f(sm['rms_az_mrad'], '.2f')} / {_f(sm['rms_el_mrad'], '.2f')} mrad"
        "</b></div>"
        f"<div>paper grid search az / el<b>{_f(sm['grid_rms_az_mrad'], '.2f')} / "
        f"{_f(sm['grid_rms_el_mrad'], '.2f')} mrad</b></div>"
        f"<div>total time<b>{_f(sm['seconds'], '.0f')} s</b></div>"
        "</div>"
    )
    files = plan.get("files", {})
    map_png = next((v for v in files.values() if str(v).endswith(".png")), None)
    plan_html = (
        "<h2>Flight plan</h2>"
        f"<p>{plan['passes']} UFACET passes ({plan['feasible_passes']} feasible), {plan['waypoints']} waypoints, "
        f"{e(images_text(plan))}; {plan['flights']} flight(s). Planned in "
        f"{_f(plan['seconds'], '.1f')} s. Autopilot files: "
        + ", ".join(f"<a href=\"{e(str(v))}\">{e(Path(str(v)).name)}</a>" for v in files.values()) + ".</p>"
        + (_img(str(map_png), "plan map", "wide") if map_png else "")
    )
    refused = ""
    if doc.get("refused_pairs"):
        refused = ("<p class=note>Pairs the renderer refused (replaced by the next): "
                   + "; ".join(e(r) for r in doc["refused_pairs"]) + "</p>")
    pairs = "\n".join(_pair_section(p) for p in doc["pairs"])
    return head + intro + plan_html + refused + pairs + "</body></html>\n"


def write_report(path: str | Path, doc: dict[str, Any]) -> Path:
    """Write :func:`render_report` of ``doc`` to ``path`` atomically."""
    from pihim._atomic import atomic_path

    with atomic_path(path) as tmp:
        Path(tmp).write_text(render_report(doc), encoding="utf-8")
    return Path(path)
