"""The Python names ../shared/spec/interfaces.md promises import from the paths it gives them."""
from __future__ import annotations

import re

import pytest

import lcpr_core
import lcpr_core.detector
import lcpr_core.lcpr.detector
from lcpr_common.shared_data import shared_dir

INTERFACE_IMPORTS = (
    "from lcpr_core import LCPR, range_image, SequenceModel, DescriptorModel, structure_feature, lidar_slices",
    "from lcpr_core import Describer, ModelConfig",
    "from lcpr_core.detector import LoopDetector, DetectorConfig, Frame",
    "from lcpr_core.pretrained import default_weights",
    "from lcpr_core import GeometricVerifier, VerifierConfig",
    "from msg_tools import pointcloud2_to_array, image_to_array",
)


@pytest.mark.parametrize("statement", INTERFACE_IMPORTS)
def test_every_interface_import_statement_runs(statement: str) -> None:
    exec(statement, {})  # an ImportError fails the test


def test_the_interface_imports_here_are_those_of_the_spec_when_it_is_at_hand() -> None:
    root = shared_dir(marker="spec")
    if root is None:
        pytest.skip("../shared/spec not found")
    text = (root / "spec" / "interfaces.md").read_text()
    spec = {re.sub(r"\s*#.*$", "", line).strip() for line in text.splitlines()
            if re.match(r"\s*from (lcpr_core|msg_tools)\S* import ", line)}
    assert spec == set(INTERFACE_IMPORTS)


def test_the_stable_detector_path_re_exports_the_classes_of_lcprs_folder() -> None:
    for name in lcpr_core.detector.__all__:
        assert getattr(lcpr_core.detector, name) is getattr(lcpr_core.lcpr.detector, name)
    assert lcpr_core.Describer is lcpr_core.lcpr.Describer
