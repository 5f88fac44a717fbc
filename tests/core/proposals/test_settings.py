import dataclasses
import json

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from factorydet_core.detection.detector import Detector, params_for
from factorydet_core.detection.model import DetectionModel
from factorydet_core.proposals.settings import (
    PRESETS,
    FrontEndParams,
    front_end_from_record,
    front_end_params,
    preset_for,
)
from factorydet_core.types import InputError


@settings(max_examples=40, deadline=None)
@given(
    preset=st.sampled_from(sorted(PRESETS)),
    history=st.integers(0, 3),
    voxel=st.floats(0.05, 1.0, allow_nan=False),
    crop_z=st.one_of(st.none(), st.tuples(st.floats(-2, 0), st.floats(0.5, 6))),
    scales=st.lists(st.floats(0.5, 4.0), min_size=1, max_size=3).map(tuple),
)
def test_settings_survive_json_whole(preset, history, voxel, crop_z, scales):
    params = PRESETS[preset].replace(
        history_frames=history, voxel_size_m=voxel, crop_z_m=crop_z, proposal_scales_m=scales
    )
    back = FrontEndParams.from_dict(json.loads(json.dumps(params.to_dict())))
    assert back == params


def test_from_dict_keeps_defaults_for_missing_names_and_rejects_unknown_ones():
    values = PRESETS["indoor"].to_dict()
    del values["include_patches"], values["segmentation"]["k_graph"]
    back = FrontEndParams.from_dict(values)
    assert back.include_patches == FrontEndParams().include_patches
    assert back.segmentation.k_graph == FrontEndParams().segmentation.k_graph
    assert back.voxel_size_m == PRESETS["indoor"].voxel_size_m
    # A segmentation setting given at the top level (as ``replace`` and ``--set`` take it) is kept.
    assert FrontEndParams.from_dict({"k_graph": 5}).segmentation.k_graph == 5
    nested = FrontEndParams.from_dict({"k_graph": 5, "segmentation": {"k_features": 12}}).segmentation
    assert (nested.k_graph, nested.k_features) == (5, 12)
    with pytest.raises(InputError, match="unknown parameter"):
        FrontEndParams.from_dict({"voxel_size": 0.3})
    with pytest.raises(InputError, match="unknown segmentation setting"):
        FrontEndParams.from_dict({"segmentation": {"kgraph": 3}})
    with pytest.raises(InputError, match="voxel_size_m"):
        FrontEndParams.from_dict({"voxel_size_m": -1})


def test_one_rule_picks_the_preset():
    assert preset_for(12) == "agv" and preset_for(1) == "indoor"
    assert front_end_params(num_sensors=12) == PRESETS["agv"]
    assert front_end_params(num_sensors=1) == PRESETS["indoor"]
    assert front_end_params("agv", {"k_graph": 7}).segmentation.k_graph == 7
    with pytest.raises(InputError, match="unknown preset 'outdoor'"):
        front_end_params("outdoor")


def test_old_records_name_a_preset_and_overrides():
    old = {"preset": "agv", "overrides": {"voxel_size_m": 0.3, "crop_z_m": [0.0, 3.0]}}
    assert front_end_from_record(old) == PRESETS["agv"].replace(voxel_size_m=0.3, crop_z_m=(0.0, 3.0))
    assert front_end_from_record({}) is None and front_end_from_record(None) is None
    assert front_end_from_record({"overrides": {}}) is None
    whole = PRESETS["indoor"].replace(history_frames=2)
    assert front_end_from_record(whole.to_dict()) == whole


def test_checkpoints_carry_the_front_half_whole(tiny_model_path, tmp_path):
    model = DetectionModel.load(tiny_model_path)
    assert model.front_end == PRESETS["agv"]  # written by the fixture
    changed = dataclasses.replace(model, front_end=PRESETS["agv"].replace(history_frames=2, k_graph=7))
    again = DetectionModel.load(changed.save(tmp_path / "changed.pt"))
    assert again.front_end == changed.front_end
    detector = Detector.for_model(again, num_sensors=12)
    assert detector.params == changed.front_end and detector.model is again
    # A model trained without a note runs on the data's preset.
    assert params_for(dataclasses.replace(again, front_end=None), 1) == PRESETS["indoor"]
    assert params_for(None, 12) == PRESETS["agv"]
