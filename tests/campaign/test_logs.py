"""Poses from flight logs: rotations, ULog and DataFlash bytes read by the libraries' readers, frame matching."""

from __future__ import annotations

import math
import struct
from datetime import datetime, timedelta, timezone

import numpy as np
import pytest

from pihim.camera.pose import CameraPose
from pihim.campaign import logs
from pihim.campaign.logs import (
    FrameRecord,
    camera_pose_from_attitude,
    gps_to_utc,
    match_frames,
    read_dataflash,
    read_frames_csv,
    read_ulog,
    utc_to_gps,
    write_dataflash,
    write_frames_csv,
    write_ulog,
)
from pihim.errors import PihimInputError
from pihim.field.geodesy import enu_to_geodetic, geodetic_to_enu, nsttf_origin

ORIGIN = nsttf_origin(1650.0)
T0 = datetime(2021, 5, 13, 19, 0, 0, tzinfo=timezone.utc).timestamp()


def _rx(a: float) -> np.ndarray:
    c, s = math.cos(math.radians(a)), math.sin(math.radians(a))
    return np.array([[1, 0, 0], [0, c, -s], [0, s, c]], float)


def _ry(a: float) -> np.ndarray:
    c, s = math.cos(math.radians(a)), math.sin(math.radians(a))
    return np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]], float)


def _rz(a: float) -> np.ndarray:
    c, s = math.cos(math.radians(a)), math.sin(math.radians(a))
    return np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]], float)


_NED_TO_ENU = np.array([[0.0, 1, 0], [1, 0, 0], [0, 0, -1]])


def _axes_by_hand(vehicle: np.ndarray, gimbal: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Camera forward, right, down in ENU: camera x/y/z through the gimbal then the vehicle (explicit matrices)."""
    m = vehicle @ gimbal
    return tuple(_NED_TO_ENU @ m[:, k] for k in range(3))  # type: ignore[return-value]


# --------------------------------------------------------------------------- rotations


@pytest.mark.parametrize("yaw,pitch,roll", [(0, 0, 0), (37.0, -25.0, 4.0), (250.0, -80.0, -12.0), (90, -60, 30)])
def test_zero_gimbal_camera_is_the_conventions_heading_pitch_roll(yaw: float, pitch: float, roll: float) -> None:
    pose = camera_pose_from_attitude([1.0, 2.0, 3.0], roll, pitch, yaw)
    ref = CameraPose.from_attitude([1.0, 2.0, 3.0], yaw, pitch, roll)
    np.testing.assert_allclose(pose.rotation, ref.rotation, atol=1e-12)


def test_body_gimbal_composes_with_the_full_vehicle_attitude() -> None:
    v = _rz(120.0) @ _ry(6.0) @ _rx(-8.0)  # vehicle yaw 120, nose up 6, left wing down 8
    g = _rz(-15.0) @ _ry(-40.0)  # gimbal yawed 15 left of the nose, pitched 40 down
    fwd, right, down = _axes_by_hand(v, g)
    pose = camera_pose_from_attitude([0, 0, 30.0], -8.0, 6.0, 120.0, gimbal_pitch_deg=-40.0, gimbal_yaw_deg=-15.0)
    np.testing.assert_allclose(pose.forward, fwd, atol=1e-12)
    np.testing.assert_allclose(pose.right, right, atol=1e-12)
    np.testing.assert_allclose(pose.down, down, atol=1e-12)


def test_stabilized_gimbal_ignores_vehicle_roll_and_pitch_but_follows_its_yaw() -> None:
    a = camera_pose_from_attitude([0, 0, 30.0], 9.0, -7.0, 200.0, gimbal_pitch_deg=-35.0, gimbal_yaw_deg=10.0,
                                  mode="stabilized")
    ref = CameraPose.from_attitude([0, 0, 30.0], 210.0, -35.0, 0.0)
    np.testing.assert_allclose(a.rotation, ref.rotation, atol=1e-12)
    e = camera_pose_from_attitude([0, 0, 30.0], 9.0, -7.0, 200.0, gimbal_pitch_deg=-35.0, gimbal_yaw_deg=10.0,
                                  mode="earth")
    np.testing.assert_allclose(e.rotation, CameraPose.from_attitude([0, 0, 30.0], 10.0, -35.0).rotation, atol=1e-12)


def test_unknown_gimbal_mode_refused() -> None:
    with pytest.raises(PihimInputError, match="gimbal mode"):
        camera_pose_from_attitude([0, 0, 1.0], 0, 0, 0, mode="sideways")


# --------------------------------------------------------------------------- time


def test_gps_time_is_utc_plus_leap_seconds() -> None:
    utc = datetime(2021, 5, 13, 19, 0, 0, 250000, tzinfo=timezone.utc)
    gps = utc + timedelta(seconds=18)  # IERS: GPS - UTC = 18 s since 2017
    delta = gps - datetime(1980, 1, 6, tzinfo=timezone.utc)
    week, rest = divmod(delta.total_seconds(), 7 * 86400)
    assert utc_to_gps(utc.timestamp()) == (int(week), int(round(rest * 1000)))
    assert gps_to_utc(int(week), rest * 1000) == pytest.approx(utc.timestamp(), abs=1e-6)


# --------------------------------------------------------------------------- a smooth synthetic flight


def _flight(n_pos: int = 51, n_att: int = 101, dur: float = 10.0):
    """Straight 4 m/s leg heading 60 deg with a constant yaw rate; gimbal pitch ramps -20 -> -50."""
    tp = T0 + np.linspace(0.0, dur, n_pos)
    ta = T0 + np.linspace(0.0, dur, n_att)
    e = 10.0 + 4.0 * np.sin(math.radians(60)) * (tp - T0)
    n = -5.0 + 4.0 * np.cos(math.radians(60)) * (tp - T0)
    u = np.full_like(tp, 25.0)
    lat, lon, h = enu_to_geodetic(np.stack([e, n, u], axis=1), ORIGIN)
    yaw = 55.0 + 1.0 * (ta - T0)  # deg, 1 deg/s
    pitch = np.full_like(ta, 3.0)
    roll = np.full_like(ta, -2.0)
    gpitch = -20.0 - 3.0 * (ta - T0)
    return tp, (lat, lon, h), ta, (yaw, pitch, roll), gpitch


def _truth_pose(t: float, mode: str = "body") -> CameraPose:
    s = t - T0
    enu = [10.0 + 4.0 * math.sin(math.radians(60)) * s, -5.0 + 4.0 * math.cos(math.radians(60)) * s, 25.0]
    return camera_pose_from_attitude(enu, -2.0, 3.0, 55.0 + s, gimbal_pitch_deg=-20.0 - 3.0 * s, mode=mode)


def _quat(yaw, pitch, roll):
    from scipy.spatial.transform import Rotation

    return Rotation.from_euler("ZYX", np.stack([yaw, pitch, roll], axis=1), degrees=True).as_quat()


def _write_test_ulog(path, gimbal: bool = True):
    tp, (lat, lon, h), ta, (yaw, pitch, roll), gpitch = _flight()
    write_ulog(path, boot_utc_s=T0 - 100.0,
               position={"t": tp, "latitude_deg": lat, "longitude_deg": lon, "height_m": h},
               attitude={"t": ta, "quat": _quat(yaw, pitch, roll)},
               gimbal={"t": ta, "quat": _quat(np.zeros_like(ta), gpitch, np.zeros_like(ta))} if gimbal else None)
    return path


def _pose_err(a: CameraPose, b: CameraPose) -> tuple[float, float]:
    d = float(np.linalg.norm(np.asarray(a.position_m) - np.asarray(b.position_m)))
    rel = np.asarray(a.rotation) @ np.asarray(b.rotation).T
    ang = math.degrees(math.acos(max(-1.0, min(1.0, (np.trace(rel) - 1) / 2))))
    return d, ang


def test_ulog_bytes_read_by_pyulog(tmp_path) -> None:
    pyulog = pytest.importorskip("pyulog")
    path = _write_test_ulog(tmp_path / "f.ulg")
    u = pyulog.ULog(str(path))
    assert not u.file_corruption
    names = {d.name for d in u.data_list}
    assert names == {"vehicle_global_position", "vehicle_gps_position", "vehicle_attitude",
                     "gimbal_device_attitude_status"}
    gps = u.get_dataset("vehicle_gps_position").data
    assert len(gps["timestamp"]) == 51
    assert gps["time_utc_usec"][0] - gps["timestamp"][0] == round((T0 - 100.0) * 1e6)
    att = u.get_dataset("vehicle_attitude").data
    q0 = _quat(np.array([55.0]), np.array([3.0]), np.array([-2.0]))[0]
    np.testing.assert_allclose([att["q[1]"][0], att["q[2]"][0], att["q[3]"][0], att["q[0]"][0]], q0, atol=1e-7)
    # pyulog's own writer round-trips the file into one our reader reads identically
    u.write_ulog(str(tmp_path / "again.ulg"))
    a, b = read_ulog(path), read_ulog(tmp_path / "again.ulg")
    np.testing.assert_array_equal(a.latitude_deg, b.latitude_deg)
    np.testing.assert_array_equal(a.attitude.as_quat(), b.attitude.as_quat())


def test_ulog_frames_matched_by_time_interpolated_and_slerped(tmp_path) -> None:
    pytest.importorskip("pyulog")
    track = read_ulog(_write_test_ulog(tmp_path / "f.ulg"))
    assert track.gimbal_mode == "stabilized"  # YAW_IN_VEHICLE_FRAME flag
    times = T0 + np.array([0.0, 0.137, 3.333, 7.91, 10.0])
    frames = [FrameRecord(f"f{k}", f"f{k}.tiff", float(t)) for k, t in enumerate(times)]
    matched = match_frames(frames, track, ORIGIN)
    assert all(m.ok for m in matched)
    for m in matched:
        d, ang = _pose_err(m.pose, _truth_pose(m.frame.time_utc_s, mode="stabilized"))
        # position linear in time, so interpolation is exact up to PX4's float32 heights (~1e-4 m at 1675 m);
        # slerp of a constant-rate yaw is exact, the gimbal pitch ramp likewise; float32 quaternions: ~1e-5 deg
        assert d < 2e-4
        assert ang < 2e-4


def test_body_and_stabilized_differ_when_the_vehicle_tilts(tmp_path) -> None:
    """Without a gimbal topic the mount is fixed (body mode): vehicle roll and pitch enter."""
    pytest.importorskip("pyulog")
    track = read_ulog(_write_test_ulog(tmp_path / "f.ulg", gimbal=False))
    assert track.gimbal is None
    m = match_frames([FrameRecord("a", "a.tiff", T0 + 2.0)], track, ORIGIN)[0]
    s = 2.0
    enu = [10.0 + 4.0 * math.sin(math.radians(60)) * s, -5.0 + 4.0 * math.cos(math.radians(60)) * s, 25.0]
    ref = CameraPose.from_attitude(enu, 57.0, 3.0, -2.0)
    assert _pose_err(m.pose, ref)[1] < 2e-4


def test_frames_outside_the_log_are_reported_not_guessed(tmp_path) -> None:
    pytest.importorskip("pyulog")
    tp, (lat, lon, h), ta, (yaw, pitch, roll), gpitch = _flight()
    gap = (tp < T0 + 4.0) | (tp > T0 + 6.5)  # 2.6 s without position fixes
    write_ulog(tmp_path / "g.ulg", boot_utc_s=T0 - 5.0,
               position={"t": tp[gap], "latitude_deg": lat[gap], "longitude_deg": lon[gap], "height_m": h[gap]},
               attitude={"t": ta, "quat": _quat(yaw, pitch, roll)})
    track = read_ulog(tmp_path / "g.ulg")
    frames = [FrameRecord("early", "e", T0 - 0.5), FrameRecord("ok", "o", T0 + 1.0),
              FrameRecord("gap", "g", T0 + 5.0), FrameRecord("late", "l", T0 + 10.2)]
    res = {m.frame.frame_id: m for m in match_frames(frames, track, ORIGIN)}
    assert res["ok"].ok
    assert res["early"].pose is None and "before the first position sample" in res["early"].reason
    assert res["gap"].pose is None and "gap of the position samples" in res["gap"].reason
    assert res["late"].pose is None and "after the last" in res["late"].reason


def test_truncated_and_garbage_ulogs_refused(tmp_path) -> None:
    pytest.importorskip("pyulog")
    good = _write_test_ulog(tmp_path / "f.ulg").read_bytes()
    (tmp_path / "garbage.ulg").write_bytes(b"ULog\x01\x12\x35\x01" + bytes(8) + b"\xff" * 200)
    with pytest.raises(PihimInputError):
        read_ulog(tmp_path / "garbage.ulg")
    (tmp_path / "head.ulg").write_bytes(good[:12])
    with pytest.raises(PihimInputError, match="not a readable PX4 ULog"):
        read_ulog(tmp_path / "head.ulg")
    # cut in the middle of a message: pyulog drops the partial message silently; the reader refuses the file
    cut = tmp_path / "cut.ulg"
    cut.write_bytes(good[: len(good) // 2 + 5])
    with pytest.raises(PihimInputError, match="truncated"):
        read_ulog(cut)


def test_ulog_without_gps_time_refused(tmp_path) -> None:
    pytest.importorskip("pyulog")
    w = logs._ULogWriter(0)
    w.fmt("vehicle_attitude", [("uint64_t", "timestamp"), ("float[4]", "q")])
    w.subscribe("vehicle_attitude")
    w.data("vehicle_attitude", {"timestamp": 1, "q": [1, 0, 0, 0]})
    (tmp_path / "a.ulg").write_bytes(bytes(w.buf))
    with pytest.raises(PihimInputError, match="time_utc_usec"):
        read_ulog(tmp_path / "a.ulg")


# --------------------------------------------------------------------------- DataFlash


def _write_test_bin(path, undulation: float = -22.0):
    tp, (lat, lon, h), ta, (yaw, pitch, roll), gpitch = _flight()
    write_dataflash(path, boot_utc_s=T0 - 60.0, geoid_undulation_m=undulation,
                    position={"t": tp, "latitude_deg": lat, "longitude_deg": lon, "height_m": h},
                    attitude={"t": ta, "yaw_deg": yaw, "pitch_deg": pitch, "roll_deg": roll},
                    gimbal={"t": ta, "yaw_deg": np.zeros_like(ta), "pitch_deg": gpitch, "roll_deg": np.zeros_like(ta)})
    return path


def test_dataflash_bytes_read_by_pymavlink(tmp_path) -> None:
    dfr = pytest.importorskip("pymavlink.DFReader")
    path = _write_test_bin(tmp_path / "f.bin")
    def first(kind: str):  # a new reader per type: DFReader caches the type filter of recv_match
        return dfr.DFReader_binary(str(path), zero_time_base=True).recv_match(type=kind)

    gps = first("GPS")
    tp, (lat, lon, h), *_ = _flight()
    assert gps.Lat == pytest.approx(lat[0], abs=1.5e-7)
    assert gps.Alt == pytest.approx(h[0] + 22.0, abs=1e-3)  # AMSL = ellipsoidal - undulation
    att = first("ATT")
    assert (att.Yaw, att.Pitch, att.Roll) == pytest.approx((55.0, 3.0, -2.0), abs=0.006)
    mnt = first("MNT")
    assert mnt.Pitch == pytest.approx(-20.0)


def test_dataflash_frames_matched(tmp_path) -> None:
    pytest.importorskip("pymavlink")
    path = _write_test_bin(tmp_path / "f.bin")
    with pytest.raises(PihimInputError, match="geoid undulation"):
        read_dataflash(path, geoid_undulation_m=None)
    track = read_dataflash(path, geoid_undulation_m=-22.0)
    assert track.gimbal_mode == "stabilized"
    frames = [FrameRecord(str(k), "x", T0 + t) for k, t in enumerate((0.05, 2.5, 9.99))]
    for m in match_frames(frames, track, ORIGIN):
        d, ang = _pose_err(m.pose, _truth_pose(m.frame.time_utc_s, mode="stabilized"))
        assert d < 0.02  # Lat/Lng in 1e-7 deg (1 cm)
        assert ang < 0.01  # ATT angles in centidegrees
    assert match_frames([FrameRecord("x", "x", T0 + 11.0)], track, ORIGIN)[0].pose is None


def test_corrupt_dataflash_refused(tmp_path) -> None:
    pytest.importorskip("pymavlink")
    (tmp_path / "x.bin").write_bytes(b"\x00" * 100)
    with pytest.raises(PihimInputError, match="not an ArduPilot DataFlash"):
        read_dataflash(tmp_path / "x.bin", geoid_undulation_m=0.0)
    good = _write_test_bin(tmp_path / "f.bin").read_bytes()
    (tmp_path / "short.bin").write_bytes(good[:300])  # the formats and a message or two only
    with pytest.raises(PihimInputError):
        read_dataflash(tmp_path / "short.bin", geoid_undulation_m=0.0)
    (tmp_path / "cut.bin").write_bytes(good[: len(good) // 2 + 5])
    with pytest.raises(PihimInputError, match="truncated"):
        read_dataflash(tmp_path / "cut.bin", geoid_undulation_m=0.0)
    bad = bytearray(good)
    i = good.index(b"\xa3\x95", len(good) // 2)  # a message header in the middle (damaged sync bytes)
    bad[i] ^= 0xFF
    (tmp_path / "flip.bin").write_bytes(bytes(bad))
    with pytest.raises(PihimInputError, match="corrupt|truncated"):
        read_dataflash(tmp_path / "flip.bin", geoid_undulation_m=0.0)


# --------------------------------------------------------------------------- frames.csv


def test_frames_csv_round_trip_and_pose(tmp_path) -> None:
    lat, lon, h = (float(v) for v in enu_to_geodetic([5.0, 6.0, 20.0], ORIGIN))
    pose = {"latitude_deg": lat, "longitude_deg": lon, "height_m": h, "roll_deg": 1.5, "pitch_deg": -2.0,
            "yaw_deg": 300.0, "gimbal_pitch_deg": -45.0, "gimbal_yaw_deg": 5.0}
    frames = [FrameRecord("0001", "frames/0001.tiff", T0 + 0.0667, pose), FrameRecord("0002", "b.tiff", T0 + 1, pose)]
    write_frames_csv(tmp_path / "frames.csv", frames)
    back = read_frames_csv(tmp_path / "frames.csv")
    assert back[0].frame_id == "0001" and back[0].time_utc_s == pytest.approx(T0 + 0.0667, abs=1e-6)
    assert back[0].pose == pytest.approx(pose)
    m = match_frames(back, None, ORIGIN)[0]
    np.testing.assert_allclose(m.pose.position_m, [5.0, 6.0, 20.0], atol=1e-6)
    v = _rz(300.0) @ _ry(-2.0) @ _rx(1.5)
    g = _rz(5.0) @ _ry(-45.0)
    fwd, right, _ = _axes_by_hand(v, g)
    np.testing.assert_allclose(m.pose.forward, fwd, atol=1e-12)
    np.testing.assert_allclose(m.pose.right, right, atol=1e-12)


@pytest.mark.parametrize("text,msg", [
    ("frame_id,file\n1,a.tiff\n", "no column time_utc"),
    ("frame_id,file,time_utc\n1,a.tiff,2021-05-13T19:00:00\n", "no UTC offset"),
    ("frame_id,file,time_utc\n1,a.tiff,2021-05-13T19:00:00Z\n1,b.tiff,2021-05-13T19:00:01Z\n", "duplicate"),
    ("frame_id,file,time_utc,latitude_deg\n1,a,2021-05-13T19:00:00Z,3\n", "all present or all absent"),
    ("frame_id,file,time_utc\n", "no frames"),
])
def test_bad_frames_csv(tmp_path, text: str, msg: str) -> None:
    (tmp_path / "frames.csv").write_text(text)
    with pytest.raises(PihimInputError, match=msg):
        read_frames_csv(tmp_path / "frames.csv")


def test_no_log_and_no_pose_is_reported() -> None:
    m = match_frames([FrameRecord("1", "a", T0)], None, ORIGIN)[0]
    assert m.pose is None and "no pose" in m.reason


def test_ulog_header_layout() -> None:
    """The file header is the spec's 16 bytes and the flag-bits message comes first (40 bytes of payload)."""
    w = logs._ULogWriter(1234)
    b = bytes(w.buf)
    assert b[:7] == b"ULog\x01\x12\x35" and b[7] == 1 and struct.unpack("<Q", b[8:16])[0] == 1234
    assert struct.unpack("<HB", b[16:19]) == (40, ord("B"))
    enu = geodetic_to_enu(ORIGIN.latitude_deg, ORIGIN.longitude_deg, ORIGIN.height_m, ORIGIN)
    np.testing.assert_allclose(enu, 0.0, atol=1e-9)


def test_gps_times_and_attitudes_that_cannot_be_are_refused() -> None:
    """NaN raised 'cannot convert float NaN to integer' or scipy's 'zero norm quaternions'; a week's worth of
    milliseconds and more was accepted."""
    for week, ms in ((math.nan, 0.0), (2160, math.inf), (2160, 604_800_000.0), (-1, 0.0), (2160, -5.0)):
        with pytest.raises(PihimInputError, match="GPS week"):
            gps_to_utc(week, ms)
    with pytest.raises(PihimInputError, match="UTC time must be a finite number"):
        utc_to_gps(math.nan)
    with pytest.raises(PihimInputError, match="angles must be finite"):
        camera_pose_from_attitude([0.0, 0.0, 30.0], 0.0, math.nan, 90.0)
    week, ms = utc_to_gps(1.62e9)
    assert gps_to_utc(week, ms) == pytest.approx(1.62e9, abs=1e-3)


def test_a_time_rounding_up_to_the_next_gps_week_carries_into_it() -> None:
    """utc_to_gps gave (week, 604800000) within 0.5 ms of a week's end, which gps_to_utc refuses (a simulated
    DataFlash log could then not be read back)."""
    week, ms = utc_to_gps(1.62e9)
    end = float(gps_to_utc(week, 604_799_999)) + 0.0008  # 0.2 ms before the week's end
    week2, ms2 = utc_to_gps(end)
    assert (week2, ms2) == (week + 1, 0) and float(gps_to_utc(week2, ms2)) == pytest.approx(end, abs=1e-3)
