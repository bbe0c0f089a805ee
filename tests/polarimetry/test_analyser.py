"""Tests for the analyser matrix (paper eq. 1 and its calibrated generalisation)."""

import json

import numpy as np
import pytest

from pihim.errors import PihimInputError
from pihim.polarimetry import AnalyserMatrix


def test_ideal_pinv_is_paper_eq1():
    w = AnalyserMatrix.ideal().pinv
    # channel order 0, 45, 90, 135
    expected = np.array([[0.5, 0.5, 0.5, 0.5], [1.0, 0.0, -1.0, 0.0], [0.0, 1.0, 0.0, -1.0]])
    assert np.allclose(w, expected, atol=1e-12)


def test_ideal_forward_model_is_malus():
    a = AnalyserMatrix.ideal()
    # fully polarized light at 30 deg: I_k = S0 cos^2(30 - theta_k)
    s0, p, aop = 2.0, 1.0, 30.0
    s = (s0, s0 * p * np.cos(np.radians(2 * aop)), s0 * p * np.sin(np.radians(2 * aop)))
    i = a.intensities(*s)
    theta = np.radians([0.0, 45.0, 90.0, 135.0])
    assert np.allclose(i, s0 * np.cos(np.radians(aop) - theta) ** 2)


def test_parameters_roundtrip():
    angles = [1.5, 44.0, 91.0, 134.2]
    t = [1.0, 0.93, 1.06, 0.97]
    er = [80.0, 150.0, 300.0, 120.0]
    a = AnalyserMatrix.from_parameters(angles, t, er)
    assert np.allclose(a.angles_deg, angles)
    assert np.allclose(a.transmission, t)
    assert np.allclose(a.extinction_ratio, er)
    # least-squares inverse recovers any Stokes vector exactly (full column rank)
    s = np.array([3.0, -0.4, 1.1])
    assert np.allclose(a.stokes(a.intensities(*s)), s)


def test_json_roundtrip(tmp_path):
    a = AnalyserMatrix.from_parameters([1, 46, 89, 136], [1.0, 0.9, 1.1, 1.0], 200.0)
    p = tmp_path / "cal.json"
    p.write_text(json.dumps(a.to_dict()))
    b = AnalyserMatrix.load(p)
    assert np.allclose(a.matrix, b.matrix)
    assert AnalyserMatrix.ideal().to_dict()["extinction_ratio"] == [None] * 4


@pytest.mark.parametrize(
    "content, match",
    [("{", "not a readable"), ("{}", "no 'matrix'"), ('{"matrix": [[1,2]]}', "4x3"), ('{"matrix": "x"}', "numeric"),
     # true was read as 1 (a matrix of the ideal analyser's shape otherwise)
     ('{"matrix": [[0.5, 0.5, 0], [0.5, 0, 0.5], [0.5, -0.5, 0], [0.5, 0, true]]}', "holds true or false"),
     ('{"matrix": [[0.5, 0.5, 0], [0.5, 0, 0.5], [0.5, -0.5, 0], [0.5, 0, NaN]]}', r"entry \[3\]\[2\] is nan")],
)
def test_bad_calibration_files(tmp_path, content, match):
    p = tmp_path / "bad.json"
    p.write_text(content)
    with pytest.raises(PihimInputError, match=match):
        AnalyserMatrix.load(p)


def test_rank_deficient_rejected():
    with pytest.raises(PihimInputError, match="rank"):
        AnalyserMatrix.from_parameters([0, 0, 90, 90])


@pytest.mark.parametrize(
    "scale, match", [(1e-300, "transmissions"), (1e300, "transmissions"), (-1.0, "transmissions")]
)
def test_implausible_scale_rejected(scale, match):
    # issue 10: a matrix of 1e-300 passed the rank test and masked every pixel (exit 0)
    with pytest.raises(PihimInputError, match=match):
        AnalyserMatrix(AnalyserMatrix.ideal().matrix * scale)


def test_ill_conditioned_rejected():
    with pytest.raises(PihimInputError, match="ill-conditioned"):
        AnalyserMatrix.from_parameters([0, 45, 90, 135], 1.0, 1.0 + 1e-7)  # polarizers that barely polarize


def test_deeply_nested_calibration_json_is_one_line(tmp_path):
    p = tmp_path / "deep.json"
    p.write_text("[" * 100_000 + "]" * 100_000)
    with pytest.raises(PihimInputError, match="nested too deeply") as err:
        AnalyserMatrix.load(p)
    assert str(p) in str(err.value)


def test_fifo_calibration_refused(tmp_path):
    import os

    p = tmp_path / "cal.json"
    os.mkfifo(p)
    with pytest.raises(PihimInputError, match="not a regular file"):
        AnalyserMatrix.load(p)
