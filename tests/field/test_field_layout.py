"""Field layout: OpenCSP CSV loading, names, spec, tower and generated fields."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial import cKDTree

from pihim.errors import PihimInputError
from pihim.field.layout import (
    HELIOSTAT_CSV_COLUMNS,
    NSTTF_BCS_STANDBY,
    NSTTF_TOWER,
    NSTTF_TOWER_TARGET,
    UFACET_AIM_POINT,
    Field,
    Heliostat,
    HeliostatSpec,
    Tower,
    canonical_name,
    grid_facet_centroids,
    load_facet_centroids,
    load_field,
    nsttf_facet_centroids,
    nsttf_like_field,
    nsttf_spec,
    parse_heliostat_name,
    radial_staggered_field,
)

SHARED = Path(__file__).resolve().parents[2].parent / "shared" / "data" / "nsttf"
HEADER = ",".join(HELIOSTAT_CSV_COLUMNS)
ROW_8E3 = "8E3,24.39,94.5,4.75,25,5,5,4.02,0.1778,1.2192,1.2192"
ROW_8E2 = "8E2,14.63,94.49,4.53,25,5,5,4.02,0.1778,1.2192,1.2192"


@pytest.fixture(scope="module")
def shared() -> Path:
    if not (SHARED / "heliostats.csv").is_file() or not (SHARED / "facet_centroids.csv").is_file():
        pytest.skip("../shared/data/nsttf is not available (fresh clone)")
    return SHARED


@pytest.fixture(scope="module")
def real_field(shared: Path) -> Field:
    return load_field(shared / "heliostats.csv", shared / "facet_centroids.csv", tower=NSTTF_TOWER)


def write(tmp_path: Path, text: str, name: str = "h.csv", bom: bool = False) -> Path:
    p = tmp_path / name
    p.write_bytes((b"\xef\xbb\xbf" if bom else b"") + text.encode("utf-8"))
    return p


# ----------------------------------------------------------------------------- the NSTTF files


def test_load_nsttf_field(real_field: Field) -> None:
    f = real_field
    assert len(f) == 218 and f.pivots.shape == (218, 3)
    assert f.heliostat("8E3") == Heliostat("8E3", 8, "E", 3, (24.39, 94.5, 4.75))
    assert f.index("8e03") == f.index("8E3")
    s = f.spec
    assert (s.rows, s.cols, s.n_facets) == (5, 5, 25)
    assert (s.facet_width_m, s.facet_height_m, s.pivot_height_m, s.pivot_offset_m) == (1.2192, 1.2192, 4.02, 0.1778)
    assert set(f.rows.tolist()) == set(range(5, 15))
    # East is +x, West is -x, columns count outward from the centre line
    assert np.all((f.pivots[:, 0] > 0) == (f.sides == "E"))
    e = f.sides == "E"
    for side in (e, ~e):
        for row in range(5, 15):
            m = side & (f.rows == row)
            order = np.argsort(f.columns[m])
            assert np.all(np.diff(np.abs(f.pivots[m, 0])[order]) > 9.0)


def test_generated_facet_centroids_match_shared_file(shared: Path) -> None:
    assert np.allclose(nsttf_facet_centroids(), load_facet_centroids(shared / "facet_centroids.csv"), atol=1e-9)


@pytest.mark.parametrize("source", ["generated", "shared"])
def test_facet_numbering(source: str, request: pytest.FixtureRequest) -> None:
    if source == "shared":
        c = load_facet_centroids(request.getfixturevalue("shared") / "facet_centroids.csv")
    else:
        c = nsttf_facet_centroids()
    x, y = c[:, 0], c[:, 1]
    assert x[0] < 0 and y[0] > 0  # facet 1: top left seen from the front
    assert x[4] > 0 and y[4] > 0 and x[20] < 0 and y[20] < 0
    assert np.allclose(c[12], 0.0)  # facet 13: centre
    assert np.allclose(x[[4, 9, 14, 19, 24]], x.max())  # right column
    assert np.allclose(y[:5], y.max())  # top row
    grid_x, grid_y = x.reshape(5, 5), y.reshape(5, 5)
    assert np.all(np.diff(grid_x, axis=1) > 1.0) and np.all(np.diff(grid_y, axis=0) < -1.0)


def test_csv_loader_tolerates_bom_and_derives_centroids(tmp_path: Path) -> None:
    h = write(tmp_path, f"{HEADER}\r\n{ROW_8E3}\r\n{ROW_8E2}\r\n\r\n", bom=True)
    fc = write(tmp_path, "Facet id,X,Y,Z\n" + "\n".join(f"{i + 1},{x},{y},{z}" for i, (x, y, z) in
                                                       enumerate(nsttf_facet_centroids())), "f.csv", bom=True)
    a = load_field(h, fc)
    b = load_field(h)  # centroids generated for a 5x5 grid of 1.2192 m facets
    assert a.names == ("8E3", "8E2") and a.spec == b.spec and a.tower is None
    assert np.array_equal(a.pivots[0], [24.39, 94.5, 4.75])


def test_other_grids_get_regular_centroids(tmp_path: Path) -> None:
    h = write(tmp_path, f"{HEADER}\n1E1,10,20,4,6,2,3,3.5,0.1,1.0,1.5\n")
    spec = load_field(h).spec
    assert spec.facet_centroids.shape == (6, 3)
    assert np.allclose(spec.facet_centroids, grid_facet_centroids(2, 3, 1.0, 1.5))
    assert spec.facet_centroids[0, 0] < 0 < spec.facet_centroids[0, 1]
    assert math.isclose(spec.mirror_width_m, 3 * 1.0 + 2 * 0.05)


# ----------------------------------------------------------------------------- malformed files

BAD_ROWS = [
    ("8E3,24.39,94.5,4.75,25,5,5,4.02,0.1778,1.2192", "expected 11 columns, got 10"),
    ("8E3,24.39,94.5,4.75,25,5,5,4.02,0.1778,1.2192,1.2192,7", "expected 11 columns, got 12"),
    ("8E3,24.39,north,4.75,25,5,5,4.02,0.1778,1.2192,1.2192", "'Y' must be a finite number"),
    ("8E3,24.39,94.5,nan,25,5,5,4.02,0.1778,1.2192,1.2192", "'Z' must be a finite number"),
    # a mistyped exponent overflowed the geometry (numpy warnings, then a misleading error or none)
    ("8E3,1e308,94.5,4.75,25,5,5,4.02,0.1778,1.2192,1.2192", "'X' must be within +-100000 m, got '1e308'"),
    ("8X3,24.39,94.5,4.75,25,5,5,4.02,0.1778,1.2192,1.2192", "is not <row><E|W><column>"),
    ("E3,24.39,94.5,4.75,25,5,5,4.02,0.1778,1.2192,1.2192", "is not <row><E|W><column>"),
    ("8E2,14.63,94.49,4.53,25,5,5,4.02,0.1778,1.2192,1.2192", "duplicate heliostat name '8E2' (first on line 2)"),
    ("8e02,14.63,94.49,4.53,25,5,5,4.02,0.1778,1.2192,1.2192", "duplicate heliostat name '8E2'"),
    ("8E4,34.1,94.5,4.9,24,5,5,4.02,0.1778,1.2192,1.2192", "Num. Facets = 24 but Num. Rows x Num. Cols = 5 x 5"),
    ("8E4,34.1,94.5,4.9,20,4,5,4.02,0.1778,1.2192,1.2192", "Num. Facets = 20 differs from 25 on line 2"),
    ("8E4,34.1,94.5,4.9,25,5,5,4.02,0.2,1.2192,1.2192", "Pivot Offset = 0.2 differs from 0.1778 on line 2"),
    ("8E4,34.1,94.5,4.9,25.5,5,5,4.02,0.1778,1.2192,1.2192", "'Num. Facets' must be an integer"),
    ("8E4,34.1,94.5,4.9,25,5,5,4.02,0.1778,0,1.2192", "'Facet Width' must be positive"),
    # issue 10: a 100000 x 100000 facet grid ended in MemoryError
    ("8E4,34.1,94.5,4.9,10000000000,100000,100000,4.02,0.1778,1.2192,1.2192",
     "Num. Facets = 10000000000 (100000 x 100000) is more than pihim handles, at most 10000 facets per heliostat "
     "(the facet table alone would take 240 GB)"),
]


@pytest.mark.parametrize(("row", "message"), BAD_ROWS)
def test_malformed_heliostat_rows_name_file_and_line(tmp_path: Path, row: str, message: str) -> None:
    # line 1 header, line 2 a good row, line 3 blank (skipped but counted), line 4 the bad row
    p = write(tmp_path, f"{HEADER}\n{ROW_8E2}\n\n{row}\n{ROW_8E3}\n")
    with pytest.raises(PihimInputError) as err:
        load_field(p)
    text = str(err.value)
    assert text.startswith(f"{p}:4: ") and message in text and "\n" not in text


@pytest.mark.parametrize(
    ("text", "expected"),
    [
        ("", "empty heliostat CSV"),
        (f"{HEADER}\n", "no heliostat rows"),
        ("Name,X,Y,Z\n8E3,1,2,3\n", ":1: heliostat CSV header must be"),
        ("\ufeffName;X;Y\n", ":1: heliostat CSV header must be"),
    ],
)
def test_malformed_heliostat_files(tmp_path: Path, text: str, expected: str) -> None:
    p = write(tmp_path, text)
    with pytest.raises(PihimInputError) as err:
        load_field(p)
    assert expected in str(err.value) and str(p) in str(err.value) and "\n" not in str(err.value)


def test_missing_file(tmp_path: Path) -> None:
    with pytest.raises(PihimInputError, match="cannot read heliostat CSV"):
        load_field(tmp_path / "nope.csv")


@pytest.mark.parametrize(
    ("rows", "expected"),
    [
        (["1,0,0,0", "2,1,0"], ":3: expected 4 columns, got 3"),
        (["1,0,0,0", "1,1,0,0"], ":3: duplicate facet id 1 (first on line 2)"),
        (["1,0,0,0", "two,1,0,0"], ":3: column 'Facet id' must be an integer"),
        (["1,0,0,0", "2,1,x,0"], ":3: column 'Y' must be a finite number"),
        (["1,0,0,0", "0,1,0,0"], ":3: column 'Facet id' must be an integer >= 1"),
        (["1,0,0,0", "3,1,0,0"], "facet ids must be 1..2; missing [2]"),
        ([], "no facet rows"),
    ],
)
def test_malformed_facet_files(tmp_path: Path, rows: list[str], expected: str) -> None:
    p = write(tmp_path, "Facet id,X,Y,Z\n" + "\n".join(rows) + "\n", "f.csv")
    with pytest.raises(PihimInputError) as err:
        load_facet_centroids(p)
    assert expected in str(err.value)
    assert str(err.value).startswith(str(p)) and "\n" not in str(err.value)


def test_facet_count_must_match_heliostat_file(tmp_path: Path) -> None:
    h = write(tmp_path, f"{HEADER}\n{ROW_8E3}\n")
    fc = write(tmp_path, "Facet id,X,Y,Z\n1,0,0,0\n2,1,0,0\n", "f.csv")
    with pytest.raises(PihimInputError, match="2 facets but h.csv says Num. Facets = 25") as err:
        load_field(h, fc)
    assert str(err.value).startswith(str(fc))


# ----------------------------------------------------------------------------- names and the Field


@pytest.mark.parametrize(
    ("name", "parsed"),
    [("8E3", (8, "E", 3)), ("14W12", (14, "W", 12)), ("5w01", (5, "W", 1)), (" 10E7 ", (10, "E", 7))],
)
def test_parse_names(name: str, parsed: tuple[int, str, int]) -> None:
    assert parse_heliostat_name(name) == parsed
    assert canonical_name(name) == f"{parsed[0]}{parsed[1]}{parsed[2]}"


@pytest.mark.parametrize("name", ["E3", "8X3", "0E1", "8E0", "8E", "", "8E3a", "8 E 3 W", 83])
def test_bad_names(name: object) -> None:
    with pytest.raises(PihimInputError, match="not a heliostat name"):
        parse_heliostat_name(name)  # type: ignore[arg-type]


def test_field_lookup_and_errors() -> None:
    f = nsttf_like_field()
    i = f.index("8E3")
    assert f.names[i] == "8E3" and "8e3" in f and "99E1" not in f and "junk" not in f
    h = f.heliostat("8E3")
    assert (h.row, h.side, h.column) == (8, "E", 3) and np.allclose(h.pivot, f.pivots[i])
    with pytest.raises(PihimInputError, match=r"unknown heliostat '4E1'.*218 heliostats.*rows 5-14"):
        f.index("4E1")
    with pytest.raises(PihimInputError, match="not a heliostat name"):
        f.heliostat("tower")
    sub = f.subset(["8E3", "7E3"])
    assert sub.names == ("8E3", "7E3") and np.array_equal(sub.pivots[1], f.pivot("7E3"))
    with pytest.raises(ValueError):
        f.pivots[0, 0] = 1.0  # read-only
    assert np.allclose(f.ground_z, f.pivots[:, 2] - 4.02)
    assert [h.name for h in f][:2] == list(f.names[:2])


def test_one_heliostat_given_twice_is_refused(tmp_path: Path) -> None:
    spec = nsttf_spec()
    with pytest.raises(PihimInputError, match="heliostats 5E1 and 5E3 have pivots 0.32 m apart, less than 0.5 m"):
        Field(("5E1", "5E2", "5E3"), [[0.0, 0.0, 0.0], [9.0, 0.0, 0.0], [0.0, 0.3, 0.1]], spec)
    Field(("5E1", "5E2"), [[0.0, 0.0, 0.0], [0.0, 0.6, 0.0]], spec)  # 0.6 m: two heliostats, however odd
    Field(("5E1", "5E2"), [[0.0, 0.0, 0.0], [0.0, 0.3, 6.0]], spec)  # one above the other (a blocking test's)
    p = write(tmp_path, f"{HEADER}\n{ROW_8E2}\n{ROW_8E3}\n" + ROW_8E3.replace("8E3", "14E99") + "\n")
    with pytest.raises(PihimInputError, match=f"^{p}: heliostats 8E3 and 14E99 have pivots 0.00 m apart"):
        load_field(p)


def test_closest_pair_agrees_with_every_pair() -> None:
    """The sort-and-sweep search finds a pair below the bound exactly when the brute force over all pairs does."""
    from pihim.field.layout import _closest_pair

    rng = np.random.default_rng(7)
    for trial in range(200):
        xy = rng.uniform(0, 20, size=(int(rng.integers(2, 60)), 2 + trial % 2))  # 2-D and 3-D points
        if trial % 3 == 0:
            xy[:, 0] = np.round(xy[:, 0])  # columns sharing x, as in a surveyed grid
        d = np.sqrt((((xy[:, None, :] - xy[None, :, :])) ** 2).sum(axis=-1))
        d[np.diag_indices(len(xy))] = np.inf
        got = _closest_pair(xy, 0.5)
        assert (got is not None) == bool((d < 0.5).any())
        if got is not None:
            i, j, dist = got
            assert i < j and dist == pytest.approx(d[i, j]) and dist < 0.5


def test_overlapping_facets_are_refused() -> None:
    c = nsttf_spec().facet_centroids.copy()
    c[24] = c[0] + [0.2, 0.0, 0.0]
    with pytest.raises(PihimInputError, match="facets 1 and 25 are 0.200 m apart, less than half a facet"):
        HeliostatSpec(5, 5, 1.2192, 1.2192, 4.02, 0.1778, c)


def test_field_validation() -> None:
    spec = nsttf_spec()
    with pytest.raises(PihimInputError, match="duplicate heliostat name '5E1'"):
        Field(("5E1", "5e01"), np.zeros((2, 3)), spec)
    with pytest.raises(PihimInputError, match="pivots must be finite with shape"):
        Field(("5E1",), np.zeros((2, 3)), spec)
    with pytest.raises(PihimInputError, match="pivots must be finite"):
        Field(("5E1",), [[0.0, np.nan, 0.0]], spec)
    with pytest.raises(PihimInputError, match="no tower"):
        _ = Field(("5E1",), np.zeros((1, 3)), spec).default_aim_point
    with pytest.raises(PihimInputError, match="facet_centroids must be finite with shape"):
        HeliostatSpec(5, 5, 1.0, 1.0, 4.0, 0.1, np.zeros((24, 3)))
    with pytest.raises(PihimInputError, match="rows must be a positive integer"):
        HeliostatSpec(0, 5, 1.0, 1.0, 4.0, 0.1, np.zeros((0, 3)))


def test_tower_and_aim_points() -> None:
    t = NSTTF_TOWER
    assert t.height_m == 63.5508 and (t.x_min_m, t.x_max_m, t.y_min_m, t.y_max_m) == (-5.485, 5.485, -9.1186, 6.25)
    assert t.target == NSTTF_TOWER_TARGET == (0.0, 6.25, 63.5508)
    assert NSTTF_BCS_STANDBY == (0.0, 8.8, 28.9) and UFACET_AIM_POINT == (60.0, 8.8, 28.9)
    assert np.array_equal(nsttf_like_field().default_aim_point, [0.0, 6.25, 63.5508])
    c = t.box_corners()
    assert c.shape == (8, 3) and np.allclose(c.min(0), [-5.485, -9.1186, 0])
    assert np.allclose(c.max(0), [5.485, 6.25, 63.5508])
    assert t.box_edges().shape == (12, 2, 3)
    with pytest.raises(PihimInputError):
        Tower(height_m=-1.0)


def test_spec_dimensions() -> None:
    s = nsttf_spec()
    assert math.isclose(s.mirror_width_m, 2 * (110.004 * 0.0254 + 0.6096))
    assert math.isclose(s.mirror_height_m, 2 * (101.004 * 0.0254 + 0.6096))
    assert math.isclose(s.mirror_area_m2, 25 * 1.2192**2)
    assert s == nsttf_spec() and s != HeliostatSpec(5, 5, 1.2192, 1.2192, 4.0, 0.1778, s.facet_centroids)


# ----------------------------------------------------------------------------- generated fields


def test_nsttf_like_field_alone() -> None:
    f = nsttf_like_field()
    assert len(f) == 218 and set(f.rows.tolist()) == set(range(5, 15))
    assert np.sum(f.sides == "E") == np.sum(f.sides == "W") == 109
    x = f.pivots[:, 0]
    assert np.allclose(np.sort(x[f.rows == 5]), -np.sort(x[f.rows == 5])[::-1])  # symmetric columns
    assert (x[f.sides == "E"] > 0).all() and (x[f.sides == "W"] < 0).all()  # 8E3: East of the centre line, +x
    assert f.spec.pivot_offset_m == pytest.approx(7 * 0.0254)  # 7 in from the pivot to the mirror, in front of it
    assert f.tower is NSTTF_TOWER


def test_nsttf_like_field_close_to_real(real_field: Field) -> None:
    g = nsttf_like_field()
    real = real_field
    assert len(g) == len(real) and set(g.names) == set(real.names)
    d = g.pivots - real.pivots[real.indices(g.names)]
    assert np.max(np.hypot(d[:, 0], d[:, 1])) < 0.5  # positions of every named heliostat
    assert np.max(np.abs(d[:, 2])) < 0.7  # ground heights
    assert np.allclose(g.pivots.min(0), real.pivots.min(0), atol=0.6)  # extent
    assert np.allclose(g.pivots.max(0), real.pivots.max(0), atol=0.6)

    def spacings(f: Field) -> tuple[float, np.ndarray]:
        col = np.median(np.concatenate([np.diff(np.sort(f.pivots[f.rows == r, 0])) for r in range(5, 15)]))
        rows_y = np.array([f.pivots[f.rows == r, 1].mean() for r in range(5, 15)])
        return float(col), np.diff(rows_y)

    (cg, rg), (cr, rr) = spacings(g), spacings(real)
    assert abs(cg - cr) < 0.05 and np.max(np.abs(rg - rr)) < 1.2


def _ring_geometry(f: Field) -> tuple[np.ndarray, np.ndarray]:
    r = np.hypot(f.pivots[:, 0], f.pivots[:, 1])
    theta = np.arctan2(f.pivots[:, 0], f.pivots[:, 1])
    return r, theta


def test_radial_staggered_field_structure() -> None:
    f = radial_staggered_field(10_000)
    assert len(f) == 10_000 and len(set(f.names)) == 10_000
    spec = f.spec
    dm = math.hypot(spec.mirror_width_m, spec.mirror_height_m) + 0.5
    dist, _ = cKDTree(f.pivots[:, :2]).query(f.pivots[:, :2], k=2)
    assert dist[:, 1].min() >= dm - 1e-9  # no collisions whatever the orientations
    assert np.allclose(f.pivots[:, 2], spec.pivot_height_m)
    r, theta = _ring_geometry(f)
    rings = sorted(set(f.rows.tolist()))
    assert rings == list(range(1, len(rings) + 1))
    radius = np.array([r[f.rows == k].mean() for k in rings])
    assert np.all(np.diff(radius) > 0)
    # within a zone the angular step is constant, so the azimuthal spacing grows with the radius
    steps = []
    for k in rings[:-1]:
        t = np.sort(theta[f.rows == k])
        steps.append(np.median(np.diff(t)))
    steps = np.array(steps)
    arc = steps * radius[:-1]
    same_zone = np.isclose(steps[1:], steps[:-1])
    assert same_zone.sum() > 10 and np.all(arc[1:][same_zone] > arc[:-1][same_zone])
    assert np.any(np.isclose(steps[1:], steps[:-1] / 2))  # a new zone halves the step
    # consecutive rings of a zone are staggered by half a step
    k = int(np.flatnonzero(same_zone)[0]) + 1
    t1, t2 = np.sort(theta[f.rows == k]), np.sort(theta[f.rows == k + 1])
    off = np.min(np.abs(((t2[:, None] - t1[None, :]) + np.pi) % (2 * np.pi) - np.pi), axis=1)
    assert np.allclose(off, steps[k - 1] / 2)
    # names: row = ring, East = azimuth in [0, 180] deg, columns counted from North
    e = f.sides == "E"
    assert np.all(f.pivots[e, 0] >= -1e-9) and np.all(f.pivots[~e, 0] < 0)
    ring1_e = (f.rows == 1) & e
    assert np.all(np.diff(theta[ring1_e][np.argsort(f.columns[ring1_e])]) > 0)
    # the radial spacing grows with the distance to the tower (first-order no-blocking rule)
    assert radius[-1] - radius[-2] > radius[2] - radius[1]


def test_radial_staggered_field_options() -> None:
    f = radial_staggered_field(500, azimuth_span_deg=120.0, first_radius_m=80.0, blocking_factor=0.0)
    r, theta = _ring_geometry(f)
    assert len(f) == 500 and np.all(np.abs(np.degrees(theta)) <= 60.0 + 1e-9)
    assert math.isclose(r.min(), 80.0)
    big = radial_staggered_field(100_000, tower=Tower(height_m=200.0, target=(0.0, 0.0, 195.0)))
    assert len(big) == 100_000
    for bad in (0, -3, 2.5, True):
        with pytest.raises(PihimInputError, match="n_heliostats"):
            radial_staggered_field(bad)  # type: ignore[arg-type]
    with pytest.raises(PihimInputError, match="azimuth_span_deg"):
        radial_staggered_field(10, azimuth_span_deg=0.0)


def test_fifo_field_file_refused(tmp_path: Path) -> None:
    import os

    p = tmp_path / "h.csv"
    os.mkfifo(p)
    with pytest.raises(PihimInputError, match="not a regular file"):
        load_field(p)


def test_one_name_given_for_several_is_one_heliostat():
    """indices("5E1") read the characters "5", "E", "1" (and said "'5' is not a heliostat name")."""
    field = nsttf_like_field()
    np.testing.assert_array_equal(field.indices("5E1"), [field.index("5E1")])
    np.testing.assert_array_equal(field.indices(["5E1", "8W3"]), [field.index("5E1"), field.index("8W3")])
    assert field.subset("5E1").names == ("5E1",)


@pytest.mark.parametrize(("args", "says"), [((5, 5, -1.2, 1.2), "facet_width_m must be a finite number > 0"),
                                            ((5, 5, 1.2, 1.2, -1.0), "gap_m must be a finite number >= 0"),
                                            ((2.5, 5, 1.2, 1.2), "rows must be a positive integer"),
                                            ((5, 0, 1.2, 1.2), "cols must be a positive integer")])
def test_a_facet_grid_that_cannot_be_built_is_refused(args, says):
    """Negative sizes and gaps (overlapping facets) were accepted; rows=2.5 was a TypeError."""
    with pytest.raises(PihimInputError, match=says):
        grid_facet_centroids(*args)


def test_name_index_maps_each_name_to_its_position_and_is_read_only():
    field = nsttf_like_field()
    idx = field.name_index
    assert len(idx) == len(field) and all(idx[n] == i for i, n in enumerate(field.names))
    assert "8e03" not in idx and idx["8E3"] == field.index("8e03")  # exact names only; index() parses the rest
    with pytest.raises(TypeError):
        idx["8E3"] = 0  # type: ignore[index]
