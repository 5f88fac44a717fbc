import dataclasses
import json
import math

import pytest
from hypothesis import event, given, settings
from hypothesis import strategies as st

from factorydet_core.cli import parse_overrides
from factorydet_core.detection.detector import Detector, params_for
from factorydet_core.detection.model import DetectionModel
from factorydet_core.proposals.segment import SegmentationParams
from factorydet_core.proposals.settings import (
    MAX_EXTENT_M,
    MAX_HISTORY_FRAMES,
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
    # ...and structure split by the second cut pursuit, as the code then did.
    expected = PRESETS["agv"].replace(voxel_size_m=0.3, crop_z_m=(0.0, 3.0), split_structure=True)
    assert front_end_from_record(old) == expected
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


# Each of these reached the front half unchecked before (from a checkpoint's note, a training
# run's record, ``--set``): the first two ran for a minute and took gigabytes, the third ended in
# a traceback, the fourth was taken as a count of 1.
BAD_VALUES: dict[str, tuple[str, object]] = {
    "k_graph float 1e8": ("k_graph", 1e8),
    "k_graph 1e8": ("k_graph", 10**8),
    "k_features 1e8": ("k_features", 10**8),
    "crop_z_m to 1e300": ("crop_z_m", [0, 1e300]),
    "min_proposal_points true": ("min_proposal_points", True),
    "k_graph of 400 digits": ("k_graph", 10**400),
    "history_frames 1000": ("history_frames", 1000),
    "history_frames fraction": ("history_frames", 2.5),
    "voxel_size_m tiny": ("voxel_size_m", 1e-300),
    "voxel_size_m 100": ("voxel_size_m", 100.0),
    "voxel_size_m inf": ("voxel_size_m", float("inf")),
    "prune_m tiny": ("prune_m", 1e-9),
    "prune_m text": ("prune_m", "0.05"),
    "floor_distance_m negative": ("floor_distance_m", -0.1),
    "crop_radius_m 1e6": ("crop_radius_m", 1e6),
    "crop_z_m three": ("crop_z_m", [0.0, 1.0, 2.0]),
    "crop_z_m text": ("crop_z_m", "ab"),
    "crop_z_m mapping": ("crop_z_m", {"low": 0, "high": 1}),
    "crop_z_m equal": ("crop_z_m", [1.0, 1.0]),
    "remove_floor 1": ("remove_floor", 1),
    "include_patches text": ("include_patches", "yes"),
    "icp_between_frames null": ("icp_between_frames", None),
    "segment_on list": ("segment_on", ["points"]),
    "weighting unknown": ("weighting", "mass"),
    "feature unknown": ("feature", "raw"),
    "min_proposal_points 0": ("min_proposal_points", 0),
    "max_edge_m 1e9": ("max_edge_m", 1e9),
    "max_edge_per_range 5": ("max_edge_per_range", 5.0),
    "regularization 1e40": ("regularization", 1e40),
    "spatial_weight nan": ("spatial_weight", float("nan")),
    "min_patch_points true": ("min_patch_points", True),
    "merge_threshold 2": ("merge_threshold", 2.0),
    "convexity 0": ("convexity", 0),
    "smooth_angle_deg 180": ("smooth_angle_deg", 180.0),
    "step_m negative": ("step_m", -1.0),
    "max_object_size_m huge": ("max_object_size_m", [1e9, 1.0]),
    "max_object_size_m one": ("max_object_size_m", [4.0]),
    "structure_size_m nan": ("structure_size_m", [float("nan"), 3.0]),
    "patch_regularizations many": ("patch_regularizations", [0.1] * 100),
    "patch_regularizations zero": ("patch_regularizations", [0.0]),
    "proposal_scales_m text": ("proposal_scales_m", "1,2"),
    "proposal_sizes_m many": ("proposal_sizes_m", [[1.0, 0.5]] * 100),
    "proposal_sizes_m flat": ("proposal_sizes_m", [1.0, 0.5]),
}


@pytest.mark.parametrize("case", BAD_VALUES)
def test_every_source_refuses_a_bad_value_in_one_line_naming_it(case):
    name, value = BAD_VALUES[case]
    segmentation = name in {f.name for f in dataclasses.fields(SegmentationParams)}
    sources = {
        "--set": lambda: front_end_params("agv", parse_overrides([f"{name}={json.dumps(value)}"])),
        "overrides": lambda: front_end_params("agv", {name: value}),
        "old record": lambda: front_end_from_record({"preset": "agv", "overrides": {name: value}}),
        "whole record": lambda: front_end_from_record(
            {
                **PRESETS["agv"].to_dict(),
                **({"segmentation": {name: value}} if segmentation else {name: value}),
            }
        ),
        "code": lambda: (
            SegmentationParams(**{name: value}) if segmentation else FrontEndParams(**{name: value})
        ),
    }
    for source, build in sources.items():
        if source == "--set" and not _json_able(value):
            continue  # NaN, Inf and huge integers are not what ``json.dumps`` writes for --set
        with pytest.raises(InputError) as info:
            build()
        message = str(info.value)
        assert name in message and "\n" not in message and len(message) < 400, (source, message)


def _json_able(value: object) -> bool:
    try:
        return json.loads(json.dumps(value, allow_nan=False)) == value
    except (ValueError, TypeError):
        return False


def test_records_that_are_not_mappings_are_refused():
    for record in ([1, 2], "agv", 3, {"preset": "agv", "overrides": [["k_graph", 5]]}, {"preset": 3}):
        with pytest.raises(InputError):
            front_end_from_record(record)
    with pytest.raises(InputError, match="unknown parameter"):
        front_end_params("agv", {1: 2, "a\nb": 3})
    with pytest.raises(InputError, match="segmentation"):
        FrontEndParams.from_dict({"segmentation": [1]})
    with pytest.raises(InputError, match="segmentation"):
        FrontEndParams(segmentation={"k_graph": 5})


def test_presets_and_shipped_checkpoints_pass_the_checks():
    from factorydet_core.detection.model import DEFAULT_MODEL, PAPER_MODEL

    for name, params in PRESETS.items():
        assert FrontEndParams.from_dict(json.loads(json.dumps(params.to_dict()))) == params, name
        assert front_end_params(name) == params
    for path in (DEFAULT_MODEL, PAPER_MODEL):
        note = json.loads(path.with_suffix(".json").read_text())
        assert DetectionModel.load(path).front_end == front_end_from_record(note["front_end"])
    # The largest values allowed are taken.
    FrontEndParams(
        history_frames=MAX_HISTORY_FRAMES,
        crop_radius_m=MAX_EXTENT_M,
        crop_z_m=(-MAX_EXTENT_M, MAX_EXTENT_M),
        voxel_size_m=0.01,
        prune_m=0.001,
        segmentation=SegmentationParams(k_features=200, k_graph=100, proposal_sizes_m=[[1.0, 0.5]] * 16),
    )


_NAMES = sorted(
    {f.name for f in dataclasses.fields(FrontEndParams)}
    | {f.name for f in dataclasses.fields(SegmentationParams)}
)
_SEGMENTATION_NAMES = sorted(f.name for f in dataclasses.fields(SegmentationParams))
_JSONISH = st.recursive(
    st.one_of(
        st.none(),
        st.booleans(),
        st.integers(-3, 300),
        st.integers(-(10**400), 10**400),
        st.floats(-5.0, 50.0),
        st.floats(allow_nan=True, allow_infinity=True),
        st.sampled_from(["points", "voxels", "uniform", "direct", "aggregated", "", "x\ny"]),
    ),
    lambda children: st.one_of(
        st.lists(children, max_size=4), st.dictionaries(st.text(max_size=4), children, max_size=3)
    ),
    max_leaves=8,
)


@settings(max_examples=300, deadline=None)
@given(
    values=st.dictionaries(st.sampled_from([*_NAMES, "voxel_size", "", "a\nb"]), _JSONISH, max_size=6),
    segmentation=st.one_of(
        st.none(), _JSONISH, st.dictionaries(st.sampled_from(_SEGMENTATION_NAMES), _JSONISH)
    ),
)
def test_any_values_give_valid_settings_or_one_input_error(values, segmentation):
    """Any mapping of names to JSON-ish values (a checkpoint's note, a run's record, ``--set``)
    either makes settings that pass every check or raises one line of ``InputError``, never
    another exception."""
    record = dict(values) if segmentation is None else {**values, "segmentation": segmentation}
    for build in (
        lambda: FrontEndParams.from_dict(record),
        lambda: PRESETS["agv"].with_changes(values),
        lambda: front_end_from_record({"preset": "indoor", "overrides": values}),
    ):
        try:
            params = build()
        except InputError as exc:
            assert "\n" not in str(exc) and len(str(exc)) < 1000, str(exc)
            event("refused")
            continue
        event("accepted")
        _assert_plain_and_in_range(params)
        assert FrontEndParams.from_dict(json.loads(json.dumps(params.to_dict()))) == params


def _assert_plain_and_in_range(params: FrontEndParams) -> None:
    """Every value is of its default's kind (a bool a bool, a count an int and not a bool, a length
    a finite float) and the costly ones are within their bounds."""
    defaults = {**FrontEndParams().to_dict(), **FrontEndParams().to_dict()["segmentation"]}
    values = {**params.to_dict(), **params.to_dict()["segmentation"]}
    for name, value in values.items():
        default = defaults[name]
        if value is None:
            assert name in ("crop_radius_m", "crop_z_m", "structure_size_m", "max_points"), name
        elif isinstance(default, list):
            assert isinstance(value, list), name
        elif name != "segmentation":
            assert type(value) is type(default), (name, value)
            if isinstance(value, float):
                assert math.isfinite(value), name
    seg = params.segmentation
    assert 1 <= seg.k_features <= 200 and 1 <= seg.k_graph <= 100
    assert 0 <= params.history_frames <= MAX_HISTORY_FRAMES and 0.01 <= params.voxel_size_m <= 10
    assert params.prune_m == 0 or 0.001 <= params.prune_m <= 10
    assert params.crop_z_m is None or -MAX_EXTENT_M <= params.crop_z_m[0] < params.crop_z_m[1] <= MAX_EXTENT_M
    assert len(seg.proposal_sizes_m) <= 16 and len(seg.patch_regularizations) <= 16


def test_records_from_before_split_structure_split_structure_the_earlier_way():
    from factorydet_core.detection.model import DEFAULT_MODEL, DetectionModel
    from factorydet_core.proposals.settings import FrontEndParams, front_end_from_record

    today = FrontEndParams().to_dict()
    assert today["segmentation"]["split_structure"] is False
    older = FrontEndParams().to_dict()
    del older["segmentation"]["split_structure"]
    assert FrontEndParams.from_dict(older).segmentation.split_structure is True
    assert FrontEndParams.from_dict(today) == FrontEndParams()
    assert front_end_from_record({"preset": "agv", "overrides": {}}).segmentation.split_structure is True
    # The shipped model says how it detects (measured on the held-out factories both ways).
    assert DetectionModel.load(DEFAULT_MODEL).front_end.segmentation.split_structure is False
