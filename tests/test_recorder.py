"""Tests for harness.recorder: write .rrd files, read them back with rerun.chunk.RrdReader."""

from __future__ import annotations

import functools
import logging
from pathlib import Path

import numpy as np
import pyarrow as pa
import pytest
from rerun.chunk import Chunk, RrdReader

from harness.plant.params import SteeringParams
from harness.plant.sedan import MJCF_PATH
from harness.recorder import (
    CAR_HEIGHT_M,
    CAR_LENGTH_M,
    CAR_WIDTH_M,
    FRONT_AXLE_X_M,
    MAX_VIEWS,
    MIN_STATE_SPAN,
    REAR_AXLE_X_M,
    WHEEL_RADIUS_M,
    Recorder,
    RerunRecorder,
)

N = 1000
NAME = "step_steer"
RATIO = SteeringParams().steering_ratio
STATES = ("vx", "vy", "yaw_rate")
REPO = Path(__file__).resolve().parents[1]


def _rollout_data(n: int = N, seed: int = 0) -> dict[str, np.ndarray]:
    rng = np.random.default_rng(seed)
    t = np.arange(n) * 0.01
    states = rng.standard_normal((n, 3))
    states[5, 1] = np.nan  # NaN is allowed and must survive the round trip
    inputs = np.c_[90.0 * np.sin(t), np.where(t < 5.0, 0.3, -2.0)]
    yaw = np.linspace(0.0, 3.0, n)
    poses = np.c_[np.cumsum(np.cos(yaw)) * 0.1, np.cumsum(np.sin(yaw)) * 0.1, yaw]
    return {"time_s": t, "states": states, "inputs": inputs, "poses": poses}


def _chunks(path: Path) -> list[Chunk]:
    """All chunks of the (single) recording store of an .rrd file."""
    return RrdReader(path).stream().to_chunks()


def _temporal(chunks: list[Chunk], entity: str, component: str) -> tuple[pa.Array, pa.Array, str]:
    """(index values, component values, index name) of the temporal chunk(s) of one entity."""
    found = [
        c
        for c in chunks
        if c.entity_path == entity
        and not c.is_static
        and component in c.to_record_batch().schema.names
    ]
    assert found, f"no temporal {component} on {entity}"
    index_names = {name for c in found for name in c.timeline_names}
    assert len(index_names) == 1, index_names
    (index,) = index_names
    batches = [c.to_record_batch() for c in found]
    times = pa.concat_arrays([b.column(index) for b in batches])
    values = pa.concat_arrays([b.column(component) for b in batches])
    return times, values, index


def _static(chunks: list[Chunk], entity: str, component: str) -> list:
    """Last static value of a component on an entity."""
    found = [
        c.to_record_batch().column(component).to_pylist()[-1]
        for c in chunks
        if c.entity_path == entity and c.is_static and component in c.to_record_batch().schema.names
    ]
    assert found, f"no static {component} on {entity}"
    return found[-1]


@pytest.fixture
def written(tmp_path: Path) -> tuple[Path, dict[str, np.ndarray]]:
    """A closed recording with one full rollout and one integer-timeline series."""
    d = _rollout_data()
    t = d["time_s"]
    extra = {"ay": d["states"][:, 0] * 2.0, "pred_state": d["states"] + 1.0}
    path = tmp_path / "run" / "characterize.rrd"  # parent dir does not exist yet
    with RerunRecorder(path, steering_ratio=RATIO) as rec:
        rec.rollout(NAME, t, d["states"], d["inputs"], poses=d["poses"], extra=extra)
        rec.series("train/loss", np.arange(20), {"train": np.linspace(1, 0, 20)}, timeline="epoch")
    return path, {**d, **{f"extra_{k}": v for k, v in extra.items()}}


def test_rollout_round_trip(written: tuple[Path, dict[str, np.ndarray]]) -> None:
    """Every series lands under the documented entity path with its N values and times."""
    path, d = written
    assert path.is_file()
    assert not path.with_name(path.name + ".tmp").exists()
    reader = RrdReader(path)
    assert len(reader.recordings()) == 1
    assert reader.recordings()[0].application_id == "koopman_vehicle"
    chunks = _chunks(path)
    entities = {c.entity_path for c in chunks}
    expected = {f"/{NAME}/state/{s}" for s in ("vx", "vy", "yaw_rate")}
    expected |= {f"/{NAME}/input/{s}" for s in ("steer_wheel_deg", "pedal")}
    expected |= {f"/{NAME}/extra/ay", f"/{NAME}/extra/pred_state", f"/{NAME}/car", f"/{NAME}/path"}
    expected |= {"/train/loss/train"}
    assert expected <= entities, expected - entities

    times, values, index = _temporal(chunks, f"/{NAME}/state/vx", "Scalars:scalars")
    assert index == "sim_time"
    assert times.type == pa.duration("ns")
    assert len(values) == N
    assert all(len(v) == 1 for v in values.to_pylist())
    np.testing.assert_allclose(values.flatten().to_numpy(), d["states"][:, 0], rtol=1e-6)
    np.testing.assert_array_equal(
        times.cast(pa.int64()).to_numpy(), np.round(d["time_s"] * 1e9).astype(np.int64)
    )

    _, vy, _ = _temporal(chunks, f"/{NAME}/state/vy", "Scalars:scalars")
    np.testing.assert_allclose(vy.flatten().to_numpy(zero_copy_only=False), d["states"][:, 1])
    assert np.isnan(vy.flatten().to_numpy(zero_copy_only=False)[5])

    _, pedal, _ = _temporal(chunks, f"/{NAME}/input/pedal", "Scalars:scalars")
    np.testing.assert_allclose(pedal.flatten().to_numpy(), d["inputs"][:, 1])

    # (N, k) extra: k scalars per row.
    _, pred, _ = _temporal(chunks, f"/{NAME}/extra/pred_state", "Scalars:scalars")
    np.testing.assert_allclose(
        np.asarray(pred.to_pylist(), dtype=float), d["extra_pred_state"], rtol=1e-6
    )
    assert _static(chunks, f"/{NAME}/extra/pred_state", "SeriesLines:names") == [
        "pred_state[0]",
        "pred_state[1]",
        "pred_state[2]",
    ]
    assert _static(chunks, f"/{NAME}/state/vx", "SeriesLines:names") == ["vx"]


def test_series_are_bulk_logged_on_their_timeline_only(
    written: tuple[Path, dict[str, np.ndarray]],
) -> None:
    """send_columns adds no log_time/log_tick timelines; per-row rr.log would."""
    path, _ = written
    chunks = _chunks(path)
    vx = [c for c in chunks if c.entity_path == f"/{NAME}/state/vx" and not c.is_static]
    assert [c.timeline_names for c in vx] == [["sim_time"]]
    assert sum(c.num_rows for c in vx) == N

    times, values, index = _temporal(chunks, "/train/loss/train", "Scalars:scalars")
    assert index == "epoch"
    assert times.type == pa.int64()  # integer time_s -> sequence timeline
    np.testing.assert_array_equal(times.to_numpy(), np.arange(20))
    np.testing.assert_allclose(values.flatten().to_numpy(), np.linspace(1, 0, 20))


def test_car_pose_and_path(written: tuple[Path, dict[str, np.ndarray]]) -> None:
    """The car (body under a cabin) is sized as documented; its transform follows the poses."""
    path, d = written
    chunks = _chunks(path)
    car = f"/{NAME}/car"
    half = np.asarray(_static(chunks, f"{car}/body", "Boxes3D:half_sizes"))
    center = np.asarray(_static(chunks, f"{car}/body", "Boxes3D:centers"))
    np.testing.assert_allclose(2 * half[0, :2], [CAR_LENGTH_M, CAR_WIDTH_M], rtol=1e-6)
    np.testing.assert_allclose(center[:, :2].max(axis=0)[1], 0.0)  # centred on the pose
    np.testing.assert_allclose(np.max(center[:, 2] + half[:, 2]), CAR_HEIGHT_M, rtol=1e-6)
    assert center[1, 2] > center[0, 2]  # the cabin sits on the body

    _, trans, index = _temporal(chunks, car, "Transform3D:translation")
    assert index == "sim_time"
    assert len(trans) == N
    xyz = np.asarray([row[0] for row in trans.to_pylist()])
    np.testing.assert_allclose(xyz[:, :2], d["poses"][:, :2], rtol=1e-5, atol=1e-5)
    np.testing.assert_allclose(xyz[:, 2], 0.0)
    _, quat, _ = _temporal(chunks, car, "Transform3D:quaternion")
    q = np.asarray([row[0] for row in quat.to_pylist()])  # xyzw
    yaw = 2.0 * np.arctan2(q[:, 2], q[:, 3])
    np.testing.assert_allclose(yaw, d["poses"][:, 2], atol=1e-5)
    np.testing.assert_allclose(q[:, :2], 0.0)

    strips = _static(chunks, f"/{NAME}/path", "LineStrips3D:strips")
    assert len(strips) == 1
    pts = np.asarray(strips[0])
    assert pts.shape == (N, 3)
    np.testing.assert_allclose(pts[:, :2], d["poses"][:, :2], rtol=1e-5, atol=1e-5)


def _wheel_yaw(chunks: list[Chunk], entity: str) -> np.ndarray:
    """Yaw [rad] of a wheel's transform at every sample."""
    _, quat, _ = _temporal(chunks, entity, "Transform3D:quaternion")
    q = np.asarray([row[0] for row in quat.to_pylist()])  # xyzw
    np.testing.assert_allclose(q[:, :2], 0.0)
    return 2.0 * np.arctan2(q[:, 2], q[:, 3])


def test_the_front_wheels_steer_by_the_road_wheel_angle(
    written: tuple[Path, dict[str, np.ndarray]],
) -> None:
    """Front wheels turn by steer_wheel_deg / steering ratio at every sample; rear ones do not."""
    path, d = written
    chunks = _chunks(path)
    road_wheel = np.deg2rad(d["inputs"][:, 0]) / RATIO
    for corner in ("fl", "fr"):
        wheel = f"/{NAME}/car/wheel_{corner}"
        np.testing.assert_allclose(_wheel_yaw(chunks, wheel), road_wheel, atol=1e-6)
        _, trans, _ = _temporal(chunks, wheel, "Transform3D:translation")
        (x, y, z), *others = [row[0] for row in trans.to_pylist()]
        assert all(other == [x, y, z] for other in others)  # the axle does not move
        assert (x, np.sign(y)) == pytest.approx((FRONT_AXLE_X_M, 1 if corner == "fl" else -1))
        assert z == pytest.approx(WHEEL_RADIUS_M)
    for corner in ("rl", "rr"):
        wheel = f"/{NAME}/car/wheel_{corner}"
        x, y, _ = _static(chunks, wheel, "Transform3D:translation")[0]
        assert (x, np.sign(y)) == pytest.approx((REAR_AXLE_X_M, 1 if corner == "rl" else -1))
        assert not any(c.entity_path == wheel and not c.is_static for c in chunks)
    assert _static(chunks, f"/{NAME}/car/wheel_fl", "Cylinders3D:radii") == [
        pytest.approx(WHEEL_RADIUS_M)
    ]


def test_the_drawn_wheels_sit_where_the_plant_has_them() -> None:
    """Axles and tyre radius of the drawing are the MJCF's (models/mjcf/sedan.xml)."""
    mujoco = pytest.importorskip("mujoco")
    model = mujoco.MjModel.from_xml_path(str(MJCF_PATH))
    assert model.body("corner_fl").pos[0] == pytest.approx(FRONT_AXLE_X_M)
    assert model.body("corner_rl").pos[0] == pytest.approx(REAR_AXLE_X_M)
    tyre = model.geom_size[model.body("wheel_fl").geomadr[0]][0]
    assert tyre == pytest.approx(WHEEL_RADIUS_M)


def test_without_a_steering_ratio_the_front_wheels_point_ahead(tmp_path: Path) -> None:
    """recorder.steering_ratio unset: the wheels are drawn straight, never at a guessed angle."""
    d = _rollout_data(30)
    path = tmp_path / "straight.rrd"
    with RerunRecorder(path) as rec:
        rec.rollout("r", d["time_s"], d["states"], d["inputs"], poses=d["poses"])
    np.testing.assert_allclose(_wheel_yaw(_chunks(path), "/r/car/wheel_fl"), 0.0)
    for bad in (0.0, -16.0, float("nan")):
        with pytest.raises(ValueError, match="steering_ratio"):
            RerunRecorder(tmp_path / "bad.rrd", steering_ratio=bad)


def _blueprint(path: Path) -> dict[str, dict[str, list]]:
    """Every entity of the file's blueprint store: {component: its last value}."""
    reader = RrdReader(path)
    stores = reader.blueprints()
    assert len(stores) == 1, stores
    found: dict[str, dict[str, list]] = {}
    for c in reader.stream(store=stores[0]).to_chunks():
        b = c.to_record_batch()
        for name in b.schema.names:
            if ":" in name and not name.startswith("rerun."):
                found.setdefault(c.entity_path, {})[name] = b.column(name).to_pylist()[-1]
    return found


def _views(path: Path) -> list[dict]:
    """Every view of the blueprint: kind, origin, name, content queries and y range."""
    store = _blueprint(path)
    views = []
    for entity, values in store.items():
        if "ViewBlueprint:class_identifier" in values:
            axis = store.get(f"{entity}/ScalarAxis", {}).get("ScalarAxis:range")
            views.append(
                {
                    "entity": entity,
                    "kind": values["ViewBlueprint:class_identifier"][0],
                    "origin": values["ViewBlueprint:space_origin"][0],
                    "name": values["ViewBlueprint:display_name"][0],
                    "contents": store[f"{entity}/ViewContents"]["ViewContents:query"],
                    "y_range": None if axis is None else tuple(axis[0]),
                }
            )
    return views


def _shows(view: dict, entity: str) -> bool:
    """Whether a view's content queries (``$origin``, ``/**`` subtrees, ``- `` exclusions)
    take in ``entity``: what the viewer draws in it."""

    def matches(rule: str) -> bool:
        rule = rule.replace("$origin", view["origin"])
        if rule.endswith("/**"):
            base = rule[: -len("/**")]
            return entity == base or entity.startswith(base + "/")
        return entity == rule

    rules = [r.strip() for r in view["contents"]]
    included = any(matches(r.removeprefix("+ ")) for r in rules if not r.startswith("- "))
    return included and not any(matches(r[2:]) for r in rules if r.startswith("- "))


def _blueprint_views(path: Path) -> list[tuple[str, str]]:
    """(class identifier, space origin) of every view in the file's blueprint store."""
    return [(v["kind"], v["origin"]) for v in _views(path)]


def test_blueprint_is_in_the_file(written: tuple[Path, dict[str, np.ndarray]]) -> None:
    """The default layout is stored in the .rrd (a blueprint store), one view per series."""
    path, _ = written
    views = _blueprint_views(path)
    assert ("3D", f"/{NAME}") in views
    for s in ("state/vx", "state/vy", "state/yaw_rate", "input/steer_wheel_deg", "input/pedal"):
        assert ("TimeSeries", f"/{NAME}/{s}") in views
    assert ("TimeSeries", f"/{NAME}/extra/ay") in views
    assert ("TimeSeries", "/train/loss") in views


def test_rollout_without_pose_has_no_3d(tmp_path: Path) -> None:
    """Without poses there is no car, no path and no 3D view."""
    d = _rollout_data(50)
    path = tmp_path / "a.rrd"
    with RerunRecorder(path) as rec:
        rec.rollout("no_pose", d["time_s"], d["states"], d["inputs"])
    entities = {c.entity_path for c in _chunks(path)}
    assert "/no_pose/state/vx" in entities
    assert "/no_pose/car" not in entities
    assert "/no_pose/path" not in entities
    kinds = {k for k, _ in _blueprint_views(path)}
    assert kinds == {"TimeSeries"}


def test_null_recorder_writes_nothing(tmp_path: Path) -> None:
    """recorder=none accepts the same calls and creates no file."""
    d = _rollout_data(10)
    with Recorder(path=tmp_path / "x.rrd", application_id="whatever") as rec:
        rec.rollout("r", d["time_s"], d["states"], d["inputs"], poses=d["poses"])
        rec.series("s", np.arange(3), {"a": np.zeros(3)})
    assert list(tmp_path.iterdir()) == []


def test_partials_are_called_the_same_way(tmp_path: Path) -> None:
    """Hydra `_partial_: true` configs for both recorders accept `path=` at run time; the
    Rerun one takes the plant's steering ratio."""
    hydra_utils = pytest.importorskip("hydra.utils")
    omegaconf = pytest.importorskip("omegaconf")
    made = {}
    for name in ("rerun", "none"):
        cfg = omegaconf.OmegaConf.create(
            {
                "plant": {"steering": {"steering_ratio": 14.5}},
                "recorder": omegaconf.OmegaConf.load(REPO / "conf" / "recorder" / f"{name}.yaml"),
            }
        )
        factory = hydra_utils.instantiate(cfg.recorder)
        assert isinstance(factory, functools.partial)
        rec = factory(path=tmp_path / f"{name}.rrd")
        rec.close()
        made[name] = rec
    assert type(made["rerun"]) is RerunRecorder
    assert made["rerun"].steering_ratio == 14.5
    assert type(made["none"]) is Recorder
    assert sorted(p.name for p in tmp_path.iterdir()) == ["rerun.rrd"]


def test_tmp_file_until_close(tmp_path: Path) -> None:
    """Data goes to a .tmp file; only close() publishes the final .rrd (atomic rename)."""
    path = tmp_path / "a.rrd"
    tmp = tmp_path / "a.rrd.tmp"
    d = _rollout_data(20)
    rec = RerunRecorder(path)
    rec.rollout("r", d["time_s"], d["states"], d["inputs"])
    assert tmp.exists()
    assert not path.exists()
    rec.close()
    assert path.exists()
    assert not tmp.exists()
    assert RrdReader(path).store().summary()  # footer/manifest written: file is complete
    rec.close()  # idempotent
    assert path.exists()
    with pytest.raises(RuntimeError, match="closed"):
        rec.rollout("r2", d["time_s"], d["states"], d["inputs"])


def test_two_recorders_do_not_mix(tmp_path: Path) -> None:
    """Each recorder has its own stream; interleaved logging stays in its own file."""
    d = _rollout_data(30)
    a, b = RerunRecorder(tmp_path / "a.rrd"), RerunRecorder(tmp_path / "b.rrd")
    a.rollout("only_a", d["time_s"], d["states"], d["inputs"])
    b.rollout("only_b", d["time_s"], d["states"], d["inputs"])
    a.series("sa", np.arange(4), {"v": np.ones(4)}, timeline="step")
    b.close()
    a.close()
    ea = {c.entity_path.split("/")[1] for c in _chunks(tmp_path / "a.rrd")}
    eb = {c.entity_path.split("/")[1] for c in _chunks(tmp_path / "b.rrd")}
    assert {"only_a", "sa"} <= ea
    assert "only_b" not in ea
    assert "only_b" in eb
    assert not {"only_a", "sa"} & eb


_D = _rollout_data(40)


@pytest.mark.parametrize(
    ("kwargs", "argname"),
    [
        ({"time_s": _D["time_s"][:, None]}, "time_s"),
        ({"time_s": np.array([])}, "time_s"),
        ({"time_s": np.r_[_D["time_s"][:-1], np.nan]}, "time_s"),
        ({"states": _D["states"][:-1]}, "states"),
        ({"states": _D["states"][:, :2]}, "states"),
        ({"inputs": _D["inputs"][1:]}, "inputs"),
        ({"inputs": _D["inputs"][:, 0]}, "inputs"),
        ({"poses": _D["poses"][:, :2]}, "poses"),
        ({"poses": _D["poses"][:-3]}, "poses"),
        ({"extra": {"ay": np.zeros(39)}}, "extra"),
        ({"extra": {"ay": np.zeros((40, 2, 2))}}, "extra"),
    ],
)
def test_shape_mismatch_raises_and_logs_nothing(
    tmp_path: Path, kwargs: dict[str, object], argname: str
) -> None:
    """A bad argument is named in a one-line ValueError, and nothing of the call is logged."""
    path = tmp_path / "bad.rrd"
    args = {k: _D[k] for k in ("time_s", "states", "inputs", "poses")} | kwargs
    with RerunRecorder(path) as rec:
        with pytest.raises(ValueError, match=argname) as err:
            rec.rollout("bad", **args)  # type: ignore[arg-type]
        assert "\n" not in str(err.value)
    assert not any(c.entity_path.startswith("/bad") for c in _chunks(path))


def test_series_and_name_errors(tmp_path: Path) -> None:
    """Series shape, timeline-kind conflicts and duplicate/empty names raise ValueError."""
    d = _rollout_data(10)
    with RerunRecorder(tmp_path / "e.rrd") as rec:
        with pytest.raises(ValueError, match="values"):
            rec.series("loss", np.arange(5), {"train": np.zeros(4)}, timeline="epoch")
        with pytest.raises(ValueError, match="time_s"):
            rec.series("loss", np.zeros((5, 1)), {"train": np.zeros(5)}, timeline="epoch")
        rec.series("loss", np.arange(5), {"train": np.zeros(5)}, timeline="epoch")
        with pytest.raises(ValueError, match="epoch"):  # float time on a sequence timeline
            rec.series("other", np.linspace(0, 1, 5), {"x": np.zeros(5)}, timeline="epoch")
        with pytest.raises(ValueError, match="sim_time"):  # int time on the duration timeline
            rec.series("other", np.arange(5), {"x": np.zeros(5)})
        rec.rollout("r", d["time_s"], d["states"], d["inputs"])
        with pytest.raises(ValueError, match="already"):
            rec.rollout("r", d["time_s"], d["states"], d["inputs"])
        with pytest.raises(ValueError, match="empty"):
            rec.rollout("/", d["time_s"], d["states"], d["inputs"])


def test_custom_names_and_escaping(tmp_path: Path) -> None:
    """Custom state names and names needing escaping map to the documented entity paths."""
    d = _rollout_data(15)
    path = tmp_path / "c.rrd"
    with RerunRecorder(path) as rec:
        rec.rollout(
            "sweep/run 1",
            d["time_s"],
            d["states"][:, :2],
            d["inputs"][:, :1],
            state_names=("u", "v"),
            input_names=("delta",),
        )
    entities = {c.entity_path for c in _chunks(path)}
    assert {"/sweep/run\\ 1/state/u", "/sweep/run\\ 1/state/v"} <= entities
    assert "/sweep/run\\ 1/input/delta" in entities


def test_a_course_and_the_path_ahead_are_drawn_in_the_3d_view(tmp_path: Path) -> None:
    """Static cones and lane lines, and a predicted path that changes at every sample."""
    d = _rollout_data(50)
    ahead = d["poses"][:, None, :2] + np.arange(11)[None, :, None] * 0.5  # (T, 11, 2)
    ahead[-1] = np.nan  # the last sample has no prediction: skipped
    path = tmp_path / "course.rrd"
    with RerunRecorder(path) as rec:
        rec.rollout("lane_change", d["time_s"], d["states"], d["inputs"], poses=d["poses"])
        rec.scene("lane_change", "cones", points=np.array([[1.0, 2.0], [3.0, 4.0]]))
        rec.scene("lane_change", "lanes", strips=[np.array([[0.0, 1.0], [10.0, 1.0]])])
        rec.path_ahead("lane_change", d["time_s"], ahead)
        with pytest.raises(ValueError, match="paths must be"):
            rec.path_ahead("lane_change", d["time_s"], ahead[:, :, :1])
    chunks = _chunks(path)
    cones = np.asarray(_static(chunks, "/lane_change/scene/cones", "Points3D:positions"))
    np.testing.assert_allclose(cones[:, :2], [[1.0, 2.0], [3.0, 4.0]])
    lanes = _static(chunks, "/lane_change/scene/lanes", "LineStrips3D:strips")
    np.testing.assert_allclose(np.asarray(lanes[0])[:, :2], [[0.0, 1.0], [10.0, 1.0]])
    _, strips, _ = _temporal(chunks, "/lane_change/predicted_path", "LineStrips3D:strips")
    assert len(strips) == 49  # one path per sample with a prediction
    first = np.asarray(strips.to_pylist()[0][0])
    np.testing.assert_allclose(first[:, :2], ahead[0], rtol=1e-6)


def test_tabs_follow_priority_then_logging_order(tmp_path: Path) -> None:
    """The recording opens on its result: higher priority first, ties in logged order."""
    d = _rollout_data(20)
    path = tmp_path / "order.rrd"
    with RerunRecorder(path) as rec:
        for name, priority in (("data", 0), ("test_drive", 1), ("lane_change", 2), ("more", 0)):
            rec.rollout(name, d["time_s"], d["states"], d["inputs"], priority=priority)
        blueprint = rec.blueprint()
    assert blueprint is not None and blueprint.root_container is not None
    tabs = [tab.name for tab in blueprint.root_container.contents]
    assert tabs == ["lane_change", "test_drive", "data", "more"]


def test_the_default_layout_stops_at_its_view_budget_highest_priority_first(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    """A viewer refuses a recording whose layout has too many views: tabs are added by priority
    until MAX_VIEWS, the rest are named in one log line, and every rollout is still logged."""
    d = _rollout_data(20)
    per_tab = 1 + 3 + 2  # the car, three states, two inputs
    count = MAX_VIEWS // per_tab + 5
    path = tmp_path / "many.rrd"
    with caplog.at_level(logging.INFO, logger="harness.recorder"), RerunRecorder(path) as rec:
        for i in range(count):
            rec.rollout(f"drive_{i:03d}", d["time_s"], d["states"], d["inputs"], poses=d["poses"])
        rec.rollout(
            "lane_change", d["time_s"], d["states"], d["inputs"], poses=d["poses"], priority=2
        )
        blueprint = rec.blueprint()
    assert blueprint is not None and blueprint.root_container is not None
    tabs = [tab.name for tab in blueprint.root_container.contents]
    assert tabs[0] == "lane_change" and len(tabs) == MAX_VIEWS // per_tab
    assert tabs[1:] == [f"drive_{i:03d}" for i in range(len(tabs) - 1)]
    assert f"shows {len(tabs)} of {count + 1} rollouts" in caplog.text
    assert f"drive_{count - 1:03d}" in caplog.text
    logged = {c.entity_path.split("/")[1] for c in _chunks(path)}
    assert {f"drive_{i:03d}" for i in range(count)} <= logged  # every rollout is recorded


LANE = "tracking/de_mpc/lane_change"


@pytest.fixture
def tracked(tmp_path: Path) -> tuple[Path, dict[str, np.ndarray]]:
    """A closed recording of one tracking rollout: reference, a prediction overlay, extras."""
    d = _rollout_data(200)
    d["reference"] = d["states"] + np.array([0.5, -0.1, 0.02])
    d["predicted"] = d["states"] * 1.1
    path = tmp_path / "pipeline.rrd"
    with RerunRecorder(path, steering_ratio=RATIO) as rec:
        rec.rollout(
            LANE,
            d["time_s"],
            d["states"],
            d["inputs"],
            poses=d["poses"],
            extra={"solve_time_ms": np.ones(200)},
            priority=2,
            reference=d["reference"],
            overlays={"predicted_10_ahead": d["predicted"]},
        )
    return path, d


def test_a_tracking_rollout_logs_reference_actual_and_error_named_per_state(
    tracked: tuple[Path, dict[str, np.ndarray]],
) -> None:
    """Per state: the actual state, its reference and the overlay on the state's path, the error
    (actual - reference) under error/; every line has a name, none is an index."""
    path, d = tracked
    chunks = _chunks(path)
    root = "/tracking/de_mpc/lane_change"
    for i, s in enumerate(STATES):
        expected = {
            f"{root}/state/{s}": (d["states"][:, i], "actual"),
            f"{root}/state/{s}/reference": (d["reference"][:, i], "reference"),
            f"{root}/state/{s}/predicted_10_ahead": (d["predicted"][:, i], "predicted_10_ahead"),
            f"{root}/error/{s}": (d["states"][:, i] - d["reference"][:, i], f"{s} error"),
        }
        for entity, (values, name) in expected.items():
            _, logged, _ = _temporal(chunks, entity, "Scalars:scalars")
            got = logged.flatten().to_numpy(zero_copy_only=False)
            np.testing.assert_allclose(got, values, rtol=1e-6, atol=1e-12)
            assert _static(chunks, entity, "SeriesLines:names") == [name]
    # Named series only: no line of the rollout is called "key[i]".
    names = [
        n
        for c in chunks
        if c.entity_path.startswith(root)
        and "SeriesLines:names" in c.to_record_batch().schema.names
        for n in c.to_record_batch().column("SeriesLines:names").to_pylist()[-1]
    ]
    assert names and not [n for n in names if "[" in n]
    assert not any(c.entity_path.startswith(f"{root}/extra/error") for c in chunks)


def test_the_default_view_plots_each_state_against_its_reference(
    tracked: tuple[Path, dict[str, np.ndarray]],
) -> None:
    """The first tab's view of each state draws the reference and the actual state (both logged);
    the error has its view; the steering plot's range is the steering used."""
    path, d = tracked
    root = "/tracking/de_mpc/lane_change"
    views = {v["origin"]: v for v in _views(path)}
    logged = {
        c.entity_path
        for c in _chunks(path)
        if not c.is_static and "Scalars:scalars" in c.to_record_batch().schema.names
    }
    for s in STATES:
        view = views[f"{root}/state/{s}"]
        assert view["kind"] == "TimeSeries"
        assert s in view["name"]
        drawn = {e for e in logged if _shows(view, e)}
        assert drawn == {
            f"{root}/state/{s}",
            f"{root}/state/{s}/reference",
            f"{root}/state/{s}/predicted_10_ahead",
        }
    error = views[f"{root}/error"]
    assert {e for e in logged if _shows(error, e)} == {f"{root}/error/{s}" for s in STATES}

    steering = views[f"{root}/input/steer_wheel_deg"]
    peak = np.max(np.abs(d["inputs"][:, 0]))
    low, high = steering["y_range"]
    assert low == pytest.approx(-high) and peak < high < 1.25 * peak  # fits, centred on 0
    assert f"peak {peak:.0f}" in steering["name"]
    pedal_low, pedal_high = views[f"{root}/input/pedal"]["y_range"]
    assert pedal_low < d["inputs"][:, 1].min() and d["inputs"][:, 1].max() < pedal_high
    # All of them are in the rollout's tab, the one the recording opens on.
    store = _blueprint(path)
    (tab,) = [e for e, v in store.items() if v.get("ContainerBlueprint:display_name") == [LANE]]
    (tabs,) = [v for v in store.values() if "ContainerBlueprint:active_tab" in v]
    assert tabs["ContainerBlueprint:active_tab"] == [tab.lstrip("/")]
    in_tab, todo = set(), [tab]
    while todo:
        for child in store[todo.pop()].get("ContainerBlueprint:contents", []):
            in_tab.add(f"/{child}")
            todo.append(f"/{child}")
    wanted = [f"{root}/state/{s}" for s in STATES] + [f"{root}/error", f"{root}/input/pedal"]
    assert {views[o]["entity"] for o in wanted} <= in_tab


def test_a_steady_state_draws_flat_and_a_quality_panel_names_its_lines(tmp_path: Path) -> None:
    """Holding 80 km/h within 0.05 m/s is drawn on a plot at least MIN_STATE_SPAN wide (a flat
    line, not a crisis filling the plot); a state that moves keeps the range it moved over. An
    extra given as named columns is one plot whose lines carry those names."""
    d = _rollout_data(200)
    states = d["states"].copy()
    states[:, 0] = 22.2 + 0.05 * np.sin(d["time_s"] * 6.0)
    states[:, 1] = np.linspace(-2.0, 2.0, 200)
    reference = np.tile([22.2, 0.0, 0.0], (200, 1))
    jerk = {"longitudinal": np.ones(200), "lateral": -np.ones(200)}
    path = tmp_path / "steady.rrd"
    with RerunRecorder(path) as rec:
        rec.rollout(
            "steady",
            d["time_s"],
            states,
            d["inputs"],
            reference=reference,
            extra={"jerk_mps3": jerk},
        )
    views = {v["origin"]: v for v in _views(path)}
    low, high = views["/steady/state/vx"]["y_range"]
    assert high - low == pytest.approx(MIN_STATE_SPAN["vx"])
    assert low < 22.15 and high > 22.25
    vy_low, vy_high = views["/steady/state/vy"]["y_range"]
    assert vy_low < -2.0 and vy_high > 2.0 and vy_high - vy_low < 5.0  # the data's, 10 % margin
    assert _static(_chunks(path), "/steady/extra/jerk_mps3", "SeriesLines:names") == [
        "longitudinal",
        "lateral",
    ]
    assert views["/steady/extra/jerk_mps3"]["kind"] == "TimeSeries"


def test_a_bad_reference_or_overlay_is_refused_before_anything_is_logged(tmp_path: Path) -> None:
    """A reference or overlay of the wrong shape, or an overlay called "reference", logs nothing."""
    d = _rollout_data(20)
    path = tmp_path / "bad.rrd"
    args = (d["time_s"], d["states"], d["inputs"])
    with RerunRecorder(path) as rec:
        with pytest.raises(ValueError, match="reference"):
            rec.rollout("bad", *args, reference=d["states"][:, :2])
        with pytest.raises(ValueError, match="overlays"):
            rec.rollout("bad", *args, overlays={"p": d["states"][1:]})
        with pytest.raises(ValueError, match="reference="):
            rec.rollout("bad", *args, overlays={"reference": d["states"]})
    assert not any(c.entity_path.startswith("/bad") for c in _chunks(path))
