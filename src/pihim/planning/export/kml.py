"""KML 2.2 overview of a plan for Google Earth (``plan.kml``).

Document layout:

* a *Home* placemark (take-off position);
* one folder per scan pass, named with its index, azimuth, altitude and
  predicted usable fraction, holding a ``LineString`` through its waypoints
  (coloured from red, 0 % usable, to green, 100 %; dashed-looking grey is not
  available in KML, so infeasible passes are drawn semi-transparent) and one
  ``Point`` placemark per **capture** waypoint whose description gives the
  heading, gimbal pitch, speed, HUA and position (the icon is rotated to the
  heading);
* one folder with a ``LineString`` per flight, if the plan has flights;
* with a :class:`~pihim.field.layout.Field`: a *Heliostats* folder with one
  point per heliostat pivot (clamped to the ground) and a *Tower* placemark,
  the tower footprint extruded to its height.

Altitudes
---------
KML ``absolute`` altitudes are heights above mean sea level (Google Earth uses
the EGM96 geoid), not the WGS84 ellipsoidal heights pihim plans in [1]_ [2]_.
Two choices (``altitude_mode``):

* ``"relativeToGround"`` (default): the waypoint's ``z_m``, its height above
  the field origin (tower base), drawn above Google Earth's terrain at each
  point. Exact where the terrain is at the origin's level; off by the local
  ground height elsewhere (a few metres across the NSTTF, whose ground rises
  ~2 m per 100 m to the East). It never draws a path underground, whatever
  the uncertainty of the site's height.
* ``"absolute"``: ellipsoidal height - geoid undulation (EGM96 geoid height,
  ``geoid_undulation_m``, default from ``plan.site`` or the NSTTF estimate
  -22 m near the NSTTF). Exact to the geoid value, but any error in the
  site's ellipsoidal height (about +/-10 m for the NSTTF default) shows up
  directly against Google Earth's terrain.

Coordinates are written ``longitude,latitude,altitude`` (KML order) with 9
decimals. Child elements follow the order of the OGC KML 2.2 schema (in a
Feature: ``name``, ``description``, ``styleUrl``, ``Style``, then the
geometry), so the file validates against ``ogckml22.xsd`` (tested with the
copy fastkml ships).

References
----------
.. [1] Open Geospatial Consortium, "OGC KML 2.2", OGC 07-147r2 (2008),
   https://www.ogc.org/standard/kml/ (``altitudeMode``: ``absolute`` is
   relative to sea level).
.. [2] Google, "KML Reference", https://developers.google.com/kml/documentation/kmlreference.
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path
from typing import Any, Literal

import numpy as np

from pihim.errors import PihimInputError
from pihim.planning.export._common import (
    check_plan,
    geoid_undulation,
    plan_counts,
    site_origin,
    write_export,
)
from pihim.planning.model import Plan, ScanPass, Waypoint, heading_0_360

__all__ = ["KML_NS", "kml_text", "write_kml", "write_kml_text"]

#: KML 2.2 namespace.
KML_NS = "http://www.opengis.net/kml/2.2"
_ARROW_ICON = "http://maps.google.com/mapfiles/kml/shapes/arrow.png"
_DOT_ICON = "http://maps.google.com/mapfiles/kml/shapes/placemark_circle.png"
_HOME_ICON = "http://maps.google.com/mapfiles/kml/shapes/homegardenbusiness.png"


class _Node:
    """An element of :class:`_Stream`: its tag, attributes, depth and whether its start tag is out."""

    __slots__ = ("attrs", "depth", "opened", "tag")

    def __init__(self, tag: str, attrib: dict[str, str], depth: int) -> None:
        self.tag = tag
        self.attrs = "".join(f' {k}="{_escape_attrib(v)}"' for k, v in attrib.items()) if attrib else ""
        self.depth = depth
        self.opened = False


class _Stream:
    """XML written as its elements are created, in the text ``ET.indent(root, space=" ")`` and ``ET.tostring``
    give for the same tree (tested against them).

    ``sub(parent, tag, text, **attrib)`` adds an element under ``parent``, which must be the last element
    created or one of its ancestors (so creation order is document order); an element with ``text`` holds no
    children. The KML of a 100,000-heliostat plan has millions of elements: an ElementTree, its indentation and
    its serialization took 16 s of it.
    """

    def __init__(self, tag: str, attrib: dict[str, str], write: Callable[[str], Any] | None = None,
                 chunk_lines: int = 1 << 15) -> None:
        self.lines: list[str] = []
        self.root = _Node(tag, attrib, 0)
        self.stack = [self.root]
        self.write = write  # with a sink, the lines go out every chunk_lines (the document is not kept whole)
        self.chunk_lines = chunk_lines
        self.written = False

    def sub(self, parent: _Node, tag: str, text: Any = None, **attrib: str) -> _Node:
        stack, lines = self.stack, self.lines
        while stack and stack[-1] is not parent:
            self._close()
        if not stack:
            raise ValueError(f"<{tag}>: its parent <{parent.tag}> is closed or holds text")
        if not parent.opened:
            lines.append(" " * parent.depth + f"<{parent.tag}{parent.attrs}>")
            parent.opened = True
        node = _Node(tag, attrib, parent.depth + 1)
        if text is None:
            stack.append(node)
        else:
            body = str(text)
            pad = " " * node.depth
            lines.append(f"{pad}<{tag}{node.attrs}>{_escape_cdata(body)}</{tag}>" if body
                         else f"{pad}<{tag}{node.attrs} />")
        if self.write is not None and len(lines) >= self.chunk_lines:
            self._flush()
        return node

    def _flush(self) -> None:
        assert self.write is not None
        if self.lines:
            self.write(("\n" if self.written else "") + "\n".join(self.lines))
            self.lines.clear()
            self.written = True

    def _close(self) -> None:
        node = self.stack.pop()
        pad = " " * node.depth
        self.lines.append(f"{pad}</{node.tag}>" if node.opened else f"{pad}<{node.tag}{node.attrs} />")

    def text(self) -> str:
        """The document; closes every open element."""
        while self.stack:
            self._close()
        return "\n".join(self.lines)

    def finish(self) -> None:
        """Close every open element and pass the rest of the document to the sink."""
        while self.stack:
            self._close()
        self._flush()


def _escape_cdata(text: str) -> str:
    if "&" in text or "<" in text or ">" in text:
        text = text.replace("&", "&amp;").replace("<", "&lt;").replace(">", "&gt;")
    return text


def _escape_attrib(text: str) -> str:
    for char, entity in (("&", "&amp;"), ("<", "&lt;"), (">", "&gt;"), ('"', "&quot;"), ("\r", "&#13;"),
                         ("\n", "&#10;"), ("\t", "&#09;")):
        text = text.replace(char, entity)
    return text


def _usable_colour(fraction: float, alpha: int = 255) -> str:
    """KML colour ``aabbggrr`` from red (0) to green (1)."""
    u = min(max(float(fraction), 0.0), 1.0)
    r, g = round(255 * (1.0 - u)), round(255 * u)
    return f"{alpha:02x}00{g:02x}{r:02x}"


def _coord(lon: float, lat: float, alt: float) -> str:
    return f"{lon:.9f},{lat:.9f},{alt:.3f}"


def _capture_description(p: ScanPass, j: int, w: Waypoint, alt_text: str) -> str:
    lines = [
        f"pass {p.index}, waypoint {j} ({w.kind})",
        f"heading {heading_0_360(w.heading_deg):.2f} deg clockwise from North",
        f"gimbal pitch {w.gimbal_pitch_deg:.2f} deg (negative = below the horizon)",
        f"speed {w.speed_m_s:.2f} m/s",
    ]
    if w.hua:
        targets = sorted({t for h, t in p.pairs if h == w.hua})
        lines.append(f"HUA {w.hua}" + (f" (targets {', '.join(targets)})" if targets else ""))
    lines.append(f"field ENU x {w.x_m:.2f} m, y {w.y_m:.2f} m, z {w.z_m:.2f} m")
    lines.append(f"WGS84 lat {w.latitude_deg:.8f}, lon {w.longitude_deg:.8f}, ellipsoidal h {w.height_m:.2f} m")
    lines.append(alt_text)
    return "\n".join(lines)


def kml_text(
    plan: Plan,
    *,
    field: Any = None,
    altitude_mode: Literal["relativeToGround", "absolute"] = "relativeToGround",
    geoid_undulation_m: float | None = None,
) -> str:
    """The KML document text (see :func:`write_kml`)."""
    pieces: list[str] = []
    write_kml_text(plan, pieces.append, field=field, altitude_mode=altitude_mode,
                   geoid_undulation_m=geoid_undulation_m)
    return "".join(pieces)


def write_kml_text(
    plan: Plan,
    write: Callable[[str], Any],
    *,
    field: Any = None,
    altitude_mode: Literal["relativeToGround", "absolute"] = "relativeToGround",
    geoid_undulation_m: float | None = None,
) -> None:
    """:func:`kml_text` passed to ``write`` (e.g. a text file's) in pieces of about a megabyte.

    The plan and options are checked before the first piece. The KML of a
    100,000-heliostat plan (210 MB, millions of lines) then never lies in
    memory whole.
    """
    check_plan(plan)
    if altitude_mode not in ("relativeToGround", "absolute"):
        raise PihimInputError(f"altitude_mode must be 'relativeToGround' or 'absolute', got {altitude_mode!r}")
    if altitude_mode == "absolute":
        undulation = geoid_undulation(plan, geoid_undulation_m)

        def alt(w: Waypoint) -> float:
            return w.height_m - undulation

        alt_note = f"altitude: above mean sea level (ellipsoidal height - {undulation:.2f} m geoid undulation)"
    else:

        def alt(w: Waypoint) -> float:
            return w.z_m

        alt_note = "altitude: height above the field origin (tower base), drawn above the terrain"
    origin = None
    if field is not None:
        from pihim.field.layout import Field

        if not isinstance(field, Field):
            raise PihimInputError(f"field must be a pihim Field, got {type(field).__name__}")
        origin = site_origin(plan)

    counts = plan_counts(plan)
    write('<?xml version="1.0" encoding="UTF-8"?>\n')
    stream = _Stream("kml", {"xmlns": KML_NS}, write)
    _sub = stream.sub
    doc = _sub(stream.root, "Document")
    _sub(doc, "name", f"pihim plan {plan.time_iso}")
    _sub(doc, "open", 1)
    headline = (f"{counts['passes']} passes, {counts['flights']} flights, {counts['heliostats']} heliostats "
                f"({counts['huas']} HUAs), {counts['capture_waypoints']} images, "
                f"{100 * counts['usable_fraction']:.0f} % predicted usable")
    _sub(doc, "description", f"{headline}\n{alt_note}")
    look = _sub(doc, "LookAt")
    _sub(look, "longitude", f"{plan.home.longitude_deg:.9f}")
    _sub(look, "latitude", f"{plan.home.latitude_deg:.9f}")
    _sub(look, "altitude", 0)
    _sub(look, "heading", 0)
    _sub(look, "tilt", 45)
    _sub(look, "range", 700)
    _sub(look, "altitudeMode", "relativeToGround")

    icon_styles = (("capture", _ARROW_ICON, 0.7, "ff00ffff"), ("heliostat", _DOT_ICON, 0.4, "ffd0d0d0"),
                   ("home", _HOME_ICON, 1.0, "ffffffff"))
    for sid, icon, scale, colour in icon_styles:
        st = _sub(doc, "Style", id=sid)
        ic = _sub(st, "IconStyle")
        _sub(ic, "color", colour)
        _sub(ic, "scale", scale)
        _sub(_sub(ic, "Icon"), "href", icon)
        if sid == "heliostat":
            _sub(_sub(st, "LabelStyle"), "scale", 0.5)
    tower_style = _sub(doc, "Style", id="tower")
    _sub(_sub(tower_style, "LineStyle"), "color", "ff404040")
    poly_style = _sub(tower_style, "PolyStyle")
    _sub(poly_style, "color", "c0808080")

    home = _sub(doc, "Placemark")
    _sub(home, "name", "Home (take-off)")
    _sub(home, "description", f"WGS84 lat {plan.home.latitude_deg:.8f}, lon {plan.home.longitude_deg:.8f}, "
                              f"ellipsoidal h {plan.home.height_m:.2f} m")
    _sub(home, "styleUrl", "#home")
    pt = _sub(home, "Point")
    _sub(pt, "altitudeMode", "clampToGround")
    _sub(pt, "coordinates", _coord(plan.home.longitude_deg, plan.home.latitude_deg, 0.0))

    for p in plan.passes:
        folder = _sub(doc, "Folder")
        _sub(folder, "name", f"Pass {p.index}: az {p.azimuth_deg:.1f} deg, {p.altitude_m:.1f} m, "
                             f"{100 * p.usable_fraction:.0f} % usable" + ("" if p.feasible else " (infeasible)"))
        desc = [f"{len(p.pairs)} HUA-target pairs, {len(p.heliostats)} heliostats, gimbal pitch "
                + f"{p.gimbal_pitch_deg:.1f} deg"]
        desc += [f"issue: {s}" for s in p.issues]
        _sub(folder, "description", "\n".join(desc))
        line = _sub(folder, "Placemark")
        _sub(line, "name", f"Pass {p.index} path")
        ls = _sub(_sub(line, "Style"), "LineStyle")
        _sub(ls, "color", _usable_colour(p.usable_fraction, 255 if p.feasible else 110))
        _sub(ls, "width", 4)
        geom = _sub(line, "LineString")
        _sub(geom, "tessellate", 0)
        _sub(geom, "altitudeMode", altitude_mode)
        _sub(geom, "coordinates", " ".join(_coord(w.longitude_deg, w.latitude_deg, alt(w)) for w in p.waypoints))
        for j, w in enumerate(p.waypoints):
            if not w.capture:
                continue
            pm = _sub(folder, "Placemark")
            _sub(pm, "name", f"P{p.index}.{j}" + (f" {w.hua}" if w.hua else ""))
            _sub(pm, "description", _capture_description(p, j, w, alt_note))
            _sub(pm, "styleUrl", "#capture")
            st = _sub(pm, "Style")
            _sub(_sub(st, "IconStyle"), "heading", f"{heading_0_360(w.heading_deg):.2f}")
            pt = _sub(pm, "Point")
            _sub(pt, "altitudeMode", altitude_mode)
            _sub(pt, "coordinates", _coord(w.longitude_deg, w.latitude_deg, alt(w)))

    if plan.flights:
        folder = _sub(doc, "Folder")
        _sub(folder, "name", "Flights")
        for f in plan.flights:
            if not f.waypoints:
                continue
            pm = _sub(folder, "Placemark")
            _sub(pm, "name", f"Flight {f.index}: passes {', '.join(map(str, f.pass_indices))}")
            _sub(pm, "description", f"{f.duration_s / 60:.1f} min, {f.distance_m:.0f} m, "
                                    f"{f.heliostats_assessed} heliostats assessed")
            ls = _sub(_sub(pm, "Style"), "LineStyle")
            _sub(ls, "color", "ffff9933")
            _sub(ls, "width", 2)
            geom = _sub(pm, "LineString")
            _sub(geom, "altitudeMode", altitude_mode)
            _sub(geom, "coordinates", " ".join(_coord(w.longitude_deg, w.latitude_deg, alt(w)) for w in f.waypoints))

    if field is not None and origin is not None:
        from pihim.field.geodesy import enu_to_geodetic

        folder = _sub(doc, "Folder")
        _sub(folder, "name", f"Heliostats ({len(field)})")
        if len(field):
            lat, lon, _ = enu_to_geodetic(np.asarray(field.pivots, dtype=float), origin)
            for name, la, lo in zip(field.names, np.atleast_1d(lat).tolist(), np.atleast_1d(lon).tolist(),
                                    strict=True):
                pm = _sub(folder, "Placemark")
                _sub(pm, "name", name)
                _sub(pm, "styleUrl", "#heliostat")
                pt = _sub(pm, "Point")
                _sub(pt, "altitudeMode", "clampToGround")
                _sub(pt, "coordinates", _coord(lo, la, 0.0))
        if field.tower is not None:
            t = field.tower
            corners = np.array([(t.x_min_m, t.y_min_m, 0.0), (t.x_min_m, t.y_max_m, 0.0), (t.x_max_m, t.y_max_m, 0.0),
                                (t.x_max_m, t.y_min_m, 0.0), (t.x_min_m, t.y_min_m, 0.0)])  # clockwise, closed
            lat, lon, _ = enu_to_geodetic(corners, origin)
            pm = _sub(doc, "Placemark")
            _sub(pm, "name", "Tower")
            _sub(pm, "description", f"receiver tower, {t.height_m:.2f} m high; target "
                                    f"({t.target[0]:.2f}, {t.target[1]:.2f}, {t.target[2]:.2f}) m field ENU")
            _sub(pm, "styleUrl", "#tower")
            poly = _sub(pm, "Polygon")
            _sub(poly, "extrude", 1)
            _sub(poly, "altitudeMode", "relativeToGround")
            ring = _sub(_sub(poly, "outerBoundaryIs"), "LinearRing")
            _sub(ring, "coordinates", " ".join(_coord(lo, la, t.height_m) for la, lo in
                                               zip(lat.tolist(), lon.tolist(), strict=True)))

    stream.finish()
    write("\n")


def write_kml(
    plan: Plan,
    path: str | Path,
    *,
    field: Any = None,
    altitude_mode: Literal["relativeToGround", "absolute"] = "relativeToGround",
    geoid_undulation_m: float | None = None,
) -> Path:
    """Write a KML 2.2 overview of the plan atomically.

    Parameters
    ----------
    plan : Plan
    path : str or path-like
        Output file, conventionally ``plan.kml``.
    field : Field, optional
        Adds the heliostats and the tower; needs the field origin in
        ``plan.site`` (``latitude_deg``, ``longitude_deg``, ellipsoidal
        ``height_m``).
    altitude_mode : {"relativeToGround", "absolute"}
        How waypoint altitudes are written (module docstring).
    geoid_undulation_m : float, optional
        EGM96 geoid height for ``altitude_mode="absolute"``.

    Returns
    -------
    Path
        ``path``.

    Raises
    ------
    PihimInputError
        Invalid plan or option, or a field without a site origin; no file is
        written.
    """
    text = kml_text(plan, field=field, altitude_mode=altitude_mode, geoid_undulation_m=geoid_undulation_m)
    return write_export(path, text)
