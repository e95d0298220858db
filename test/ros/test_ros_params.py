"""Parameters mirror the typed config: names, defaults, validation, the params file and the launch file."""
from __future__ import annotations

import dataclasses
import random
import xml.etree.ElementTree as ET
from pathlib import Path

import pytest
import rclpy
import yaml
from rclpy.parameter import Parameter

from lcpr_core.detector import DetectorConfig, MatchConfig
from lcpr_ros.config import NodeConfig, SyncConfig
from lcpr_ros.params import RENAMED, Settings, all_leaves, settings_from, settings_from_file
from ros_common.errors import ConfigError
from ros_common.params import build, leaves, to_yaml
from ros_common.ros_params import RuntimeParameters, declare

REPO = Path(__file__).resolve().parents[2]
PACKAGE = "lcpr_loop_closure"


def flatten(tree: dict, prefix: str = "") -> dict:
    out = {}
    for key, value in tree.items():
        if isinstance(value, dict):
            out.update(flatten(value, f"{prefix}{key}."))
        else:
            out[f"{prefix}{key}"] = value
    return out


def test_every_config_field_is_a_dotted_parameter_with_the_dataclass_default() -> None:
    found = {leaf.name: leaf.default for leaf in all_leaves()}
    assert found["model.weights"] == "bundled"  # the node's one default that differs from the Python API's
    assert DetectorConfig().model.weights == ""
    assert found["model.image_size"] == DetectorConfig().model.image_size
    assert found["match.top_k"] == MatchConfig().top_k
    assert found["match.exclude_recent_s"] == 30.0
    assert found["keyframe.min_interval"] == 0.5
    assert found["sync.slop"] == SyncConfig().slop
    assert found["map.path"] == "" and found["map.index"] == "flat"
    assert found["camera_topics"] == NodeConfig().camera_topics and len(found["camera_topics"]) == 6
    assert found["odom_topic"] == ""
    n_fields = sum(1 for _ in leaves(DetectorConfig())) + sum(1 for _ in leaves(NodeConfig()))
    assert len(found) == n_fields


def test_building_the_config_from_parameter_values_round_trips() -> None:
    values = {leaf.name: leaf.default for leaf in all_leaves()}
    values["match.top_k"] = 3
    values["model.image_size"] = [32, 96]
    settings = settings_from(values)
    assert settings.detector.match.top_k == 3
    assert settings.detector.model.image_size == (32, 96)
    assert settings.node == NodeConfig()
    assert dataclasses.replace(settings.detector, match=MatchConfig()) == dataclasses.replace(
        DetectorConfig(model=dataclasses.replace(DetectorConfig().model, weights="bundled", image_size=(32, 96))),
        match=MatchConfig())


@pytest.mark.parametrize(("name", "value", "reason"), [
    ("match.top_k", 0, "top_k"),
    ("model.precision", "fp16", "accepted: fp32, tf32, bf16"),
    ("model.lidar", "ouster", "unknown LiDAR preset"),
    ("map.index", "ivf", "accepted: flat, hnsw"),
    ("camera_type", "jpeg", "accepted: auto, compressed, raw"),
    ("sync.slop", -1.0, "sync"),
    ("model.num_cameras", 5, "model.num_cameras=5"),
])
def test_an_invalid_value_is_refused_with_the_dataclass_reason(name: str, value: object, reason: str) -> None:
    values = {leaf.name: leaf.default for leaf in all_leaves()}
    values[name] = value
    with pytest.raises(ConfigError, match=reason.replace(".", r"\.")):
        settings_from(values)


def test_a_config_field_of_an_unsupported_type_is_a_programming_error() -> None:
    @dataclasses.dataclass(frozen=True)
    class Bad:
        values: dict = dataclasses.field(default_factory=dict)

    with pytest.raises(TypeError, match="cannot be a ROS parameter"):
        leaves(Bad())


def test_the_params_file_lists_every_parameter_with_its_default() -> None:
    data = yaml.safe_load((REPO / "config" / "lcpr.yaml").read_text())
    (node_key,) = data
    assert node_key in ("/**", "lcpr", "/lcpr")
    params = flatten(data[node_key]["ros__parameters"])
    expected = {leaf.name: (list(leaf.default) if leaf.array else leaf.default) for leaf in all_leaves()
                if not (leaf.array and not leaf.default)}  # an empty list is left out: rcl's parser refuses it
    assert params == expected
    # and the generator writes the same content (no duplicate group keys)
    assert flatten(yaml.safe_load(to_yaml(all_leaves()))["/**"]["ros__parameters"]) == expected


def test_the_launch_file_starts_lcpr_node_named_lcpr_with_the_params_file_and_the_bundled_weights() -> None:
    root = ET.parse(REPO / "launch" / "lcpr.launch.xml").getroot()
    assert root.tag == "launch"
    args = {a.get("name"): a for a in root.findall("arg")}
    assert args["weights"].get("default") == "bundled"
    (node,) = root.findall("node")
    assert (node.get("pkg"), node.get("exec"), node.get("name")) == (PACKAGE, "lcpr_node", "lcpr")
    params = node.findall("param")
    files = [p.get("from") for p in params if p.get("from")]
    assert files == [f"$(find-pkg-share {PACKAGE})/config/lcpr.yaml"]
    assert (REPO / "config" / "lcpr.yaml").is_file()
    named = {p.get("name"): p.get("value") for p in params if p.get("name")}
    assert named["model.weights"] == "$(var weights)"
    assert set(named) <= {leaf.name for leaf in all_leaves()}


# -- on a real rclpy node (no DDS traffic) ---------------------------------------------------------
@pytest.fixture
def context():
    ctx = rclpy.Context()
    rclpy.init(context=ctx, domain_id=random.randint(1, 100))
    yield ctx
    rclpy.try_shutdown(context=ctx)


def test_overrides_outside_a_range_or_of_the_wrong_type_refuse_the_start(context) -> None:
    for override, reason in ((Parameter("match.top_k", value=0), "out of range"),
                             (Parameter("match.max_distance", value=1), "decimal point"),
                             (Parameter("match.max_distance", value=3.0), "out of range")):
        node = rclpy.create_node("lcpr", context=context, parameter_overrides=[override])
        try:
            with pytest.raises(ConfigError, match=reason):
                declare(node, all_leaves())
        finally:
            node.destroy_node()


def test_run_time_changes_are_validated_by_building_the_config(context) -> None:
    node = rclpy.create_node("lcpr", context=context)
    applied: list[Settings] = []
    try:
        leaves_ = all_leaves()
        settings_from(declare(node, leaves_))
        RuntimeParameters(node, leaves_, applied.append, build=settings_from)
        ok = node.set_parameters([Parameter("match.top_k", value=7)])[0]
        assert ok.successful and applied[-1].detector.match.top_k == 7
        refused = node.set_parameters([Parameter("sync.min_cameras", value=7)])[0]
        assert not refused.successful and "sync.min_cameras=7" in refused.reason
        out_of_range = node.set_parameters([Parameter("match.max_distance", value=5.0)])[0]
        assert not out_of_range.successful and "out of range" in out_of_range.reason
        read_only = node.set_parameters([Parameter("model.weights", value="x.pth")])[0]
        assert not read_only.successful and "read-only" in read_only.reason
        assert node.get_parameter("match.max_distance").value == -1.0  # automatic
        assert len(applied) == 1
        descriptor = node.describe_parameter("match.top_k")
        assert descriptor.description and descriptor.integer_range[0].from_value == 1
    finally:
        node.destroy_node()


def test_build_keeps_defaults_for_absent_names() -> None:
    assert build(SyncConfig, {"sync.slop": 0.1}, "sync.") == SyncConfig(slop=0.1)


def test_a_lidar_no_preset_knows_is_described_by_parameters_alone() -> None:
    """model.lidar custom + model.lidar_geometry.* + model.range_size: the range image follows them."""
    import numpy as np

    from lcpr_core.lcpr.preprocess import LidarPreset, range_image

    values = {leaf.name: leaf.default for leaf in all_leaves()}
    values.update({"model.lidar": "custom", "model.range_size": [24, 512], "model.lidar_geometry.fov_up_deg": 2.0,
                   "model.lidar_geometry.fov_down_deg": -24.9, "model.lidar_geometry.yaw_offset_deg": 90.0,
                   "model.lidar_geometry.max_range": 150.0, "model.lidar_geometry.min_xy": 0.5})
    preset = settings_from(values).detector.model.range_preset
    assert preset == LidarPreset(yaw_offset_deg=90.0, min_xy=0.5, fov_up_deg=2.0, fov_down_deg=-24.9, height=24,
                                 width=512, max_range=150.0)
    points = np.random.default_rng(0).uniform(-100, 100, (5000, 3)) * [1, 1, 0.1]
    image = range_image(points, preset=preset)
    assert image.shape == (24, 512) and image.max() < 150.0 and image.max() > 80.0  # 80 m: the default would cut


@pytest.mark.parametrize(("changes", "reason"), [
    ({"model.lidar": "custom"}, "needs range_size"),
    ({"model.lidar": "custom", "model.range_size": [16, 256], "model.lidar_geometry.fov_up_deg": -40.0},
     "lidar_geometry.fov_up_deg=-40.0 must be above"),
    ({"model.lidar": "custom", "model.range_size": [16, 256], "model.lidar_geometry.max_range": 0.0},
     "lidar_geometry.max_range=0.0"),
])
def test_an_inconsistent_custom_lidar_is_refused_naming_the_value(changes: dict, reason: str) -> None:
    values = {leaf.name: leaf.default for leaf in all_leaves()}
    values.update(changes)
    with pytest.raises(ConfigError, match=reason.replace(".", r"\.").replace("[", r"\[")):
        settings_from(values)


@pytest.mark.parametrize("preset", ["ouster_os1_64", "ouster_os1_128", "ouster_os2_128", "hesai_pandar64"])
def test_the_ouster_and_hesai_presets_are_accepted_parameter_values(preset: str) -> None:
    values = {leaf.name: leaf.default for leaf in all_leaves()}
    values["model.lidar"] = preset
    got = settings_from(values).detector.model.range_preset
    assert got.fov_up_deg > got.fov_down_deg and got.height in (64, 128)


def test_the_old_name_map_model_still_sets_the_descriptor_tag_with_a_warning(context) -> None:
    node = rclpy.create_node("lcpr", context=context, parameter_overrides=[Parameter("map.model", value="mine")])
    try:
        values = declare(node, all_leaves(), renamed=RENAMED)
        assert values["map.descriptor_tag"] == "mine"
        assert node.get_parameter("map.descriptor_tag").value == "mine"
        assert settings_from(values).detector.map.descriptor_tag == "mine"
    finally:
        node.destroy_node()


def test_the_old_and_the_new_name_given_different_values_refuse_the_start(context) -> None:
    overrides = [Parameter("map.model", value="mine"), Parameter("map.descriptor_tag", value="theirs")]
    node = rclpy.create_node("lcpr", context=context, parameter_overrides=overrides)
    try:
        with pytest.raises(ConfigError, match="map.model='mine' and map.descriptor_tag='theirs' disagree"):
            declare(node, all_leaves(), renamed=RENAMED)
    finally:
        node.destroy_node()


def test_a_params_file_with_the_old_name_is_read_with_a_warning_and_a_clash_is_refused(tmp_path: Path) -> None:
    path = tmp_path / "old.yaml"
    path.write_text("/**:\n  ros__parameters:\n    map:\n      model: mine\n")
    with pytest.warns(FutureWarning, match="map.model is deprecated, use map.descriptor_tag"):
        assert settings_from_file(path).detector.map.descriptor_tag == "mine"
    path.write_text("/**:\n  ros__parameters:\n    map:\n      model: mine\n      descriptor_tag: theirs\n")
    with pytest.raises(ConfigError, match="disagree"):
        settings_from_file(path)
