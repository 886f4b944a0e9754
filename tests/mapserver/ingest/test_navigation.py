"""AUV navigation inputs: DVL, IMU and depth messages, their mounting, the complementary filter, the reader hook.

Expected numbers are computed by hand (in the comments) or by closed-form arcs, not by the code under test.
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from core.config import ConfigError
from mapserver.errors import IngestError
from mapserver.ingest import open_log
from mapserver.ingest.fusion import ComplementaryFilter, fuse, merge_samples
from mapserver.ingest.navigation import (
    IMU_TYPE,
    ODOMETRY_TYPE,
    POSE_COV_TYPE,
    PRESSURE_TYPE,
    TWIST_COV_TYPE,
    TWIST_TYPE,
    DepthSample,
    DvlSample,
    ImuSample,
    Mount,
    NavParams,
    depth_sample,
    dvl_sample,
    imu_sample,
    mount_from_tree,
    parse_nav_params,
    reports_covariance,
    rpy_matrix,
    sensor_mount,
    static_tree,
)
from mapserver.ingest.survey import survey_log
from mapserver.ingest.writer import write_log
from tests.mapserver.ingest.conftest import ROS2, T0_NS, frame_images

T = ROS2.types
S = 1_000_000_000


def _header(stamp: int, frame: str) -> Any:
    return T["std_msgs/msg/Header"](stamp=T["builtin_interfaces/msg/Time"](sec=stamp // S, nanosec=stamp % S),
                                    frame_id=frame)  # fmt: skip


def _vec(x: float, y: float, z: float) -> Any:
    return T["geometry_msgs/msg/Vector3"](x=x, y=y, z=z)


def _quat(yaw: float) -> Any:
    return T["geometry_msgs/msg/Quaternion"](x=0.0, y=0.0, z=math.sin(yaw / 2), w=math.cos(yaw / 2))


def twist_cov(v: tuple[float, float, float], variance: float, stamp: int = 0, frame: str = "dvl") -> Any:
    cov = np.zeros(36)
    cov[[0, 7, 14]] = variance
    twist = T["geometry_msgs/msg/Twist"](linear=_vec(*v), angular=_vec(0, 0, 0))
    return T[TWIST_COV_TYPE](header=_header(stamp, frame),
                             twist=T["geometry_msgs/msg/TwistWithCovariance"](twist=twist, covariance=cov))  # fmt: skip


def imu(yaw: float | None, rate: float | None, stamp: int = 0, frame: str = "imu") -> Any:
    ocov, wcov = np.zeros(9), np.zeros(9)
    if yaw is None:
        ocov[0] = -1.0
    if rate is None:
        wcov[0] = -1.0
    return T[IMU_TYPE](header=_header(stamp, frame), orientation=_quat(yaw or 0.0), orientation_covariance=ocov,
                       angular_velocity=_vec(0.0, 0.0, rate or 0.0), angular_velocity_covariance=wcov,
                       linear_acceleration=_vec(0, 0, 0), linear_acceleration_covariance=np.zeros(9))  # fmt: skip


def pressure(pa: float, stamp: int = 0) -> Any:
    return T[PRESSURE_TYPE](header=_header(stamp, "pressure"), fluid_pressure=pa, variance=4.0)


# -- messages --------------------------------------------------------------------------------------------


def test_dvl_messages_and_lost_bottom_gaps() -> None:
    good = dvl_sample(twist_cov((0.5, -0.1, 0.02), 1e-4), TWIST_COV_TYPE, 7, covariance_reported=True)
    assert good == DvlSample(7, "dvl", (0.5, -0.1, 0.02))
    nan = twist_cov((math.nan, 0.0, 0.0), 1e-4)
    assert dvl_sample(nan, TWIST_COV_TYPE, 0, covariance_reported=True).velocity is None
    minus_one = twist_cov((0.5, 0.0, 0.0), -1.0)
    assert dvl_sample(minus_one, TWIST_COV_TYPE, 0, covariance_reported=True).velocity is None
    zero_cov = twist_cov((0.0, 0.0, 0.0), 0.0)
    # a driver that reports covariance and sends zero: no fix (a gap) ...
    assert dvl_sample(zero_cov, TWIST_COV_TYPE, 0, covariance_reported=True).velocity is None
    # ... but a driver that never fills it: the zero covariance says nothing, the velocity stands
    assert dvl_sample(zero_cov, TWIST_COV_TYPE, 0, covariance_reported=False).velocity == (0.0, 0.0, 0.0)
    assert reports_covariance([(0.0, 0.0, 0.0), (1e-4, 1e-4, 1e-4)])
    assert not reports_covariance([(0.0, 0.0, 0.0), None])
    plain = T["geometry_msgs/msg/Twist"](linear=_vec(1, 2, 3), angular=_vec(0, 0, 0))
    stamped = T[TWIST_TYPE](header=_header(0, "dvl2"), twist=plain)
    assert dvl_sample(stamped, TWIST_TYPE, 0, covariance_reported=True) == DvlSample(0, "dvl2", (1.0, 2.0, 3.0))
    pose = T["geometry_msgs/msg/Pose"](position=T["geometry_msgs/msg/Point"](x=0.0, y=0.0, z=0.0),
                                       orientation=_quat(0.0))  # fmt: skip
    odom = T[ODOMETRY_TYPE](
        header=_header(0, "odom"), child_frame_id="dvl_link",
        pose=T["geometry_msgs/msg/PoseWithCovariance"](pose=pose, covariance=np.zeros(36)),
        twist=twist_cov((0.3, 0.0, 0.0), 0.0).twist,
    )  # fmt: skip
    assert dvl_sample(odom, ODOMETRY_TYPE, 0, covariance_reported=False) == DvlSample(0, "dvl_link", (0.3, 0.0, 0.0))


def test_imu_and_depth_messages() -> None:
    both = imu_sample(imu(0.4, 0.1), 5)
    assert both.orientation == pytest.approx((0.0, 0.0, math.sin(0.2), math.cos(0.2)))
    assert both.angular_velocity == (0.0, 0.0, 0.1)
    assert imu_sample(imu(None, 0.1), 5).orientation is None
    assert imu_sample(imu(0.4, None), 5).angular_velocity is None
    # 111325 Pa in fresh water (ρ 1000) under 101325 Pa: depth = 10000 / (1000 · 9.80665) = 1.0197162 m
    fresh = NavParams(water_density=1000.0)
    assert depth_sample(pressure(111325.0), PRESSURE_TYPE, 0, fresh).z == pytest.approx(-1.0197162, abs=1e-7)
    # sea water (1025), another surface pressure (100000 Pa): 120000 Pa → 20000 / 10051.816 = 1.9896902 m
    sea = NavParams(atmospheric_pa=100000.0)
    assert depth_sample(pressure(120000.0), PRESSURE_TYPE, 0, sea).z == pytest.approx(-1.9896902, abs=1e-7)
    assert depth_sample(pressure(math.nan), PRESSURE_TYPE, 0, sea).z is None
    pose = T["geometry_msgs/msg/Pose"](position=T["geometry_msgs/msg/Point"](x=9.0, y=9.0, z=-3.25),
                                       orientation=_quat(0.0))  # fmt: skip
    with_cov = T["geometry_msgs/msg/PoseWithCovariance"](pose=pose, covariance=np.zeros(36))
    pwc = T[POSE_COV_TYPE](header=_header(0, "depth"), pose=with_cov)
    assert depth_sample(pwc, POSE_COV_TYPE, 0, sea).z == -3.25


def test_nav_params_are_checked() -> None:
    params = parse_nav_params({"water_density": "1000", "dvl_rpy_deg": "180:0:45", "body_frame": "body"})
    assert params.water_density == 1000.0 and params.dvl_rpy_deg == (180.0, 0.0, 45.0) and params.body_frame == "body"
    for bad in ({"water": "1"}, {"water_density": "-1"}, {"dvl_xyz": "1:2"}, {"gravity": "nan"}):
        with pytest.raises(ConfigError):
            parse_nav_params(bad)


# -- mounting --------------------------------------------------------------------------------------------


def _tf(parent: str, child: str, xyz: tuple[float, float, float], yaw: float) -> Any:
    transform = T["geometry_msgs/msg/Transform"](translation=_vec(*xyz), rotation=_quat(yaw))
    return T["geometry_msgs/msg/TransformStamped"](header=_header(0, parent), child_frame_id=child, transform=transform)


def test_mount_from_tf_static_chain_or_parameters() -> None:
    msg = T["tf2_msgs/msg/TFMessage"](transforms=[_tf("base_link", "mast", (1.0, 0.0, 0.0), math.pi / 2),
                                                  _tf("mast", "dvl", (0.0, 2.0, 0.0), 0.0)])  # fmt: skip
    tree = static_tree([msg])
    mount = mount_from_tree(tree, "dvl", "base_link")
    assert mount is not None
    # rotation: Rz(90°); translation: (1, 0, 0) + Rz(90°)·(0, 2, 0) = (1, 0, 0) + (−2, 0, 0) = (−1, 0, 0)
    np.testing.assert_allclose(mount.rotation, [[0, -1, 0], [1, 0, 0], [0, 0, 1]], atol=1e-12)
    np.testing.assert_allclose(mount.translation, [-1.0, 0.0, 0.0], atol=1e-12)
    params = NavParams(dvl_rpy_deg=(180.0, 0.0, 0.0), dvl_xyz=(0.0, 0.0, -0.5))
    from_tf = sensor_mount(tree, "dvl", params, "dvl")
    assert from_tf.source.startswith("/tf_static")  # the log's transforms win over the parameters ...
    fallback = sensor_mount(tree, "other_dvl", params, "dvl")  # ... a frame the log lacks takes the parameters
    assert fallback.source == "parameters"
    np.testing.assert_allclose(fallback.rotation, np.diag([1.0, -1.0, -1.0]), atol=1e-12)
    np.testing.assert_allclose(fallback.translation, [0.0, 0.0, -0.5])
    assert sensor_mount(tree, "base_link", params, "dvl").source == "body frame"


# -- the filter ------------------------------------------------------------------------------------------


def _filter(dvl: Mount | None = None, has_depth: bool = False, **kw: float) -> ComplementaryFilter:
    return ComplementaryFilter(NavParams(**kw), dvl or Mount(), Mount(), has_depth=has_depth)


def test_fusion_follows_a_hand_computed_arc_through_a_rotated_lever_arm_dvl() -> None:
    # 1 m/s forward, 0.1 rad/s turn for 10 s: x = sin(1)/0.1 = 8.414710, y = (1 − cos 1)/0.1 = 4.596977, ψ = 1.
    # The DVL is turned 90° (v_body = Rz(90°)·v_dvl) 0.5 m ahead: it sees v_b + ω × r = (1, 0.05, 0), in its
    # frame Rz(−90°)·(1, 0.05, 0) = (0.05, −1, 0).
    dvl = Mount(rpy_matrix(0.0, 0.0, 90.0), np.array([0.5, 0.0, 0.0]))
    samples: list[Any] = []
    for k in range(101):
        t = k * S // 10
        samples.append(ImuSample(t, "imu", tuple(_q(0.1 * t / S)), (0.0, 0.0, 0.1)))
        samples.append(DvlSample(t, "dvl", (0.05, -1.0, 0.0)))
        samples.append(DepthSample(t, -2.0))
    states = list(fuse(merge_samples(samples), _filter(dvl, has_depth=True)))
    last = states[-1]
    assert last.stamp_ns == 10 * S
    assert (last.x, last.y, last.z, last.yaw) == pytest.approx((8.414710, 4.596977, -2.0, 1.0), abs=1e-6)


def _q(yaw: float) -> tuple[float, float, float, float]:
    return (0.0, 0.0, math.sin(yaw / 2), math.cos(yaw / 2))


def test_heading_and_depth_corrections_are_first_order_low_passes() -> None:
    f = _filter(has_depth=True, heading_tau_s=5.0, depth_tau_s=0.5)
    f.update(ImuSample(0, "imu", _q(0.0), (0.0, 0.0, 0.0)))
    f.update(DepthSample(0, -2.0))
    state = f.update(ImuSample(S, "imu", _q(0.2), (0.0, 0.0, 0.0)))
    # ψ = 0 + (1 − e^(−1/5))·0.2 = 0.181269·0.2 = 0.0362538
    assert state is not None and state.yaw == pytest.approx(0.0362538, abs=1e-7)
    state = f.update(DepthSample(S + S // 2, -3.0))
    # 1.5 s after the first depth: z = −2 + (1 − e^(−1.5/0.5))·(−1) = −2 − 0.950213 = −2.950213
    assert state is not None and state.z == pytest.approx(-2.950213, abs=1e-6)
    orientation_only = _filter()
    orientation_only.update(ImuSample(0, "imu", _q(0.0), None))
    state = orientation_only.update(ImuSample(S, "imu", _q(0.2), None))  # no gyro: the orientation is the heading
    assert state is not None and state.yaw == pytest.approx(0.2)


def test_a_dvl_dropout_is_a_gap_not_a_stop() -> None:
    def run(middle: tuple[float, float, float] | None) -> float:
        f = _filter()
        samples: list[Any] = [ImuSample(0, "imu", _q(0.0), (0.0, 0.0, 0.0))]
        for k in range(41):  # 4 s at 10 Hz; the DVL's messages in [1 s, 3 s) are `middle`
            samples.append(DvlSample(k * S // 10, "dvl", middle if 10 <= k < 30 else (1.0, 0.0, 0.0)))
        return list(fuse(merge_samples(samples), f))[-1].x

    assert run(None) == pytest.approx(4.0)  # lost bottom: the last velocity holds, 1 m/s for 4 s
    assert run((0.0, 0.0, 0.0)) == pytest.approx(2.0)  # a measured zero velocity does stop it for 2 s


def test_nothing_is_emitted_before_a_heading_and_a_depth() -> None:
    f = _filter(has_depth=True)
    assert f.update(DvlSample(0, "dvl", (1.0, 0.0, 0.0))) is None
    assert f.update(ImuSample(1, "imu", _q(0.3), None)) is None
    state = f.update(DepthSample(2, -1.0))
    assert state is not None and state.yaw == pytest.approx(0.3) and state.z == -1.0


# -- logs ------------------------------------------------------------------------------------------------


def _nav_extra(seconds: int, speed: float, yaw: float, depth_m: float, lost: range = range(0)) -> list[Any]:
    """DVL (5 Hz, frame dvl_link turned 90°: v_dvl = (0, −speed, 0)), IMU (20 Hz), pressure (10 Hz), tf_static."""
    out: list[Any] = []

    def tf(m: Any) -> Any:
        t = m.types
        quarter = t["geometry_msgs/msg/Quaternion"](x=0.0, y=0.0, z=math.sin(math.pi / 4), w=math.cos(math.pi / 4))
        transform = t["geometry_msgs/msg/Transform"](translation=m.vector(0, 0, 0), rotation=quarter)
        tr = t["geometry_msgs/msg/TransformStamped"](header=m.header(T0_NS, "base_link"), child_frame_id="dvl_link",
                                                     transform=transform)  # fmt: skip
        return t["tf2_msgs/msg/TFMessage"](transforms=[tr])

    out.append((T0_NS, "/tf_static", "tf2_msgs/msg/TFMessage", tf))
    for k in range(seconds * 20 + 1):
        stamp = T0_NS + k * S // 20

        def build_imu(m: Any, stamp: int = stamp) -> Any:
            t = m.types
            return t[IMU_TYPE](header=m.header(stamp, "imu_link"), orientation=t["geometry_msgs/msg/Quaternion"](
                x=0.0, y=0.0, z=math.sin(yaw / 2), w=math.cos(yaw / 2)), orientation_covariance=np.zeros(9),
                angular_velocity=m.vector(0, 0, 0), angular_velocity_covariance=np.zeros(9),
                linear_acceleration=m.vector(0, 0, 0), linear_acceleration_covariance=np.zeros(9))  # fmt: skip

        out.append((stamp, "/auv/imu", IMU_TYPE, build_imu))
        if k % 2 == 0:
            def build_p(m: Any, stamp: int = stamp) -> Any:
                pa = 101325.0 + 1025.0 * 9.80665 * depth_m
                return m.types[PRESSURE_TYPE](header=m.header(stamp, "p"), fluid_pressure=pa, variance=1.0)

            out.append((stamp, "/auv/pressure", PRESSURE_TYPE, build_p))
        if k % 4 == 0:
            gap = k // 4 in lost

            def build_dvl(m: Any, stamp: int = stamp, gap: bool = gap) -> Any:
                t = m.types
                cov = np.zeros(36)
                cov[[0, 7, 14]] = 0.0 if gap else 1e-4
                twist = t["geometry_msgs/msg/Twist"](linear=m.vector(0.0, 0.0 if gap else -speed, 0.0),
                                                     angular=m.vector(0, 0, 0))  # fmt: skip
                with_cov = t["geometry_msgs/msg/TwistWithCovariance"](twist=twist, covariance=cov)
                return t[TWIST_COV_TYPE](header=m.header(stamp, "dvl_link"), twist=with_cov)

            out.append((stamp, "/auv/dvl", TWIST_COV_TYPE, build_dvl))
    return out


@pytest.mark.parametrize("fmt", ["bag", "mcap"])
def test_a_log_with_dvl_imu_and_pressure_gives_the_fused_motion(tmp_path: Path, fmt: str) -> None:
    # 0.5 m/s forward for 10 s at heading 0.3 rad and 4 m depth, with DVL messages 10-19 (2 s) lost: the
    # frames' forward motions add up to 0.5 · (last frame − first frame stamp) = 0.5 · 9 s = 4.5 m, none sideways.
    images = frame_images(10, 1.0, False, offset_ns=S // 2)
    path = write_log(tmp_path / "auv", fmt, images, (), extra=_nav_extra(10, 0.5, 0.3, 4.0, range(10, 20)))  # type: ignore[arg-type]
    with open_log(path) as log:
        assert log.mapping.as_dict() == {"image": "/robot/camera/image", "odometry": None, "ground_truth": None,
                                         "dvl": "/auv/dvl", "imu": "/auv/imu", "depth": "/auv/pressure"}  # fmt: skip
        assert log.motion_source == "navigation"
        frames = list(log.frames())
        report = log.navigation_report
    assert report is not None and report.dvl_gaps == 10 and report.mounts["dvl"].startswith("/tf_static")
    assert sum(f.motion.dx for f in frames if f.motion) == pytest.approx(4.5, abs=1e-9)
    assert max(abs(f.motion.dy) + abs(f.motion.dz) + abs(f.motion.dyaw) for f in frames if f.motion) < 1e-9
    survey = survey_log(path).as_dict()
    assert survey["motion"] == "navigation" and survey["mapping"]["depth"] == "/auv/pressure"
    assert not any("visual odometry" in note for note in survey["notes"])


def test_odometry_wins_unless_switched_off_and_overrides(tmp_path: Path) -> None:
    from tests.mapserver.ingest.conftest import arc_odometry

    images = frame_images(4, 1.0, False, offset_ns=S // 2)
    path = write_log(tmp_path / "both.mcap", "mcap", images, arc_odometry(50, 10.0),
                     extra=_nav_extra(5, 0.5, 0.0, 1.0))  # fmt: skip
    with open_log(path) as log:
        assert log.motion_source == "odometry" and log.mapping.dvl == "/auv/dvl"
        assert [round(f.motion.dyaw, 6) for f in log.frames()][1] == 0.5  # the odometry's 0.5 rad/s turn
    with open_log(path, {"odometry": "none"}) as log:
        assert log.motion_source == "navigation"
        assert [round(f.motion.dx, 6) for f in log.frames()][1] == 0.5
    with open_log(path, {"odometry": "none", "depth": "none"}) as log:
        assert log.mapping.depth is None and log.motion_source == "navigation"
    with pytest.raises(IngestError, match="needs an IMU topic"):
        open_log(path, {"odometry": "none", "dvl": "/auv/dvl", "imu": "none"})
    with pytest.raises(IngestError, match="given for 'imu' has type"):
        open_log(path, {"imu": "/auv/dvl"})
    survey = survey_log(path, {"odometry": "none", "imu": "none"}).as_dict()
    assert survey["motion"] is None and any("not used" in note for note in survey["notes"])
