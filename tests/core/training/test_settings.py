"""The training settings' controls: what a flag or an app control may set, parsed and checked in
one place."""

import dataclasses

import pytest
from hypothesis import assume, given
from hypothesis import strategies as st

from factorydet_core.training.settings import (
    LOOP_CONTROLS,
    LoopSettings,
    folds_continue,
    loop_arguments,
    loop_settings_from,
)
from factorydet_core.types import InputError

CONTROLS = {c.field: c for c in LOOP_CONTROLS}


def test_every_control_shows_and_parses_back_its_default():
    defaults = LoopSettings()
    values = {c.field: c.shown(c.default) for c in LOOP_CONTROLS}
    assert loop_settings_from(values) == defaults
    for control in LOOP_CONTROLS:
        assert control.default == getattr(defaults, control.field)
        if control.kind in (int, float) and control.default is not None:
            assert control.minimum <= control.default <= control.maximum, control.field


def test_a_number_control_steps_onto_its_default_and_the_values_its_help_names():
    # A browser's number input accepts, and its arrows reach, only minimum + k * step: a step of
    # 100 from -1 offered 99, 199, ... and refused 100.
    for control in LOOP_CONTROLS:
        if control.kind not in (int, float) or control.step is None:
            continue
        shown = control.shown(control.default)
        for value in (shown, control.none_as, control.minimum, control.maximum):
            if value is None:
                continue
            steps = (value - control.minimum) / control.step
            assert abs(steps - round(steps)) < 1e-6, (control.field, value, control.step)


@given(st.sampled_from([c for c in LOOP_CONTROLS if c.kind in (int, float)]), st.floats(-1e6, 1e6))
def test_a_number_is_taken_inside_its_bounds_and_refused_outside(control, value):
    if control.kind is int:
        value = float(round(value))
    inside = control.minimum <= value <= control.maximum
    if control.none_as is not None and value == control.none_as:
        assert control.parse(value) is None
    elif inside:
        assert control.parse(value) == value
    else:
        with pytest.raises(InputError, match=control.label):
            control.parse(value)


@pytest.mark.parametrize(
    ("field", "raw", "expected"),
    [("class_weight", "none", None), ("visibility", "auto", None), ("visibility", "on", True),
     ("fragments_per_frame", 0, None), ("fragments_per_frame", 12, 12), ("geometry", False, False),
     ("recalibrate_background", 0, None), ("recalibrate_background", 0.5, 0.5),
     ("review_order", "auto", None), ("review_order", "score", "score"),
     ("review_order", "learned", "learned"),
     ("review_extra", -1, None), ("review_extra", 0, 0), ("review_extra", 300, 300)],
)  # fmt: skip
def test_choices_and_none_stand_ins(field, raw, expected):
    assert CONTROLS[field].parse(raw) == expected
    assert CONTROLS[field].shown(expected) == raw


def test_the_review_order_drop_down_lists_the_default_first():
    texts = [text for text, _ in CONTROLS["review_order"].choices]
    assert texts[0] == CONTROLS["review_order"].shown(LoopSettings().review_order) == "learned"
    assert sorted(texts) == ["auto", "class", "learned", "score"]


@pytest.mark.parametrize(
    ("values", "match"),
    [({"epochs": 2.5}, "whole number"), ({"class_weight": "heavy"}, "choose one of"),
     ({"geometry": "yes"}, "true or false"), ({"epochs": "many"}, "a number"),
     ({"num_threads": 2}, "unknown")],
)  # fmt: skip
def test_bad_values_are_one_line_errors(values, match):
    with pytest.raises(InputError, match=match):
        loop_settings_from(values)


def test_the_settings_still_check_themselves():
    with pytest.raises(InputError, match="box_quality must be on"):
        loop_settings_from({"method": "head_options", "box_quality": False})
    with pytest.raises(InputError, match="recalibrate_background applies to the learned box head"):
        loop_settings_from({"method": "paper", "recalibrate_background": 0.5})
    with pytest.raises(InputError, match="review_order must be one of score, class, learned or None"):
        LoopSettings(review_order="random")
    with pytest.raises(InputError, match="threshold_objective must be one of class, total"):
        LoopSettings(threshold_objective="micro")
    for bad in (-1, 2.5, True):
        with pytest.raises(InputError, match="review_extra must be an integer"):
            LoopSettings(review_extra=bad)
    for bad in (0, 2.5, True):
        with pytest.raises(InputError, match="quality_trees must be an integer >= 1"):
            LoopSettings(quality_trees=bad)
    for bad in (0.0, 1.5, True):  # a Python caller is checked as the controls check a flag
        with pytest.raises(InputError, match="recalibrate_background must lie in"):
            LoopSettings(recalibrate_background=bad)
    # ... and the head the loop trains gets it.
    from factorydet_core.training.loop import new_classifier

    head = new_classifier(loop_settings_from({"recalibrate_background": 0.5}), ("cube", "bar"))
    assert head.recalibrate_background == 0.5 and not head.recalibrate_by_class
    head = new_classifier(
        loop_settings_from({"recalibrate_background": 0.5, "recalibrate_by_class": True}), ("cube", "bar")
    )
    assert head.recalibrate_by_class
    with pytest.raises(InputError, match="recalibrate_by_class refines recalibrate_background"):
        loop_settings_from({"recalibrate_by_class": True})
    assert dataclasses.replace(LoopSettings(), epochs=3) == loop_settings_from({"epochs": 3})


def test_folds_continue_only_with_out_of_fold_thresholds_and_a_next_round():
    on = dataclasses.asdict(LoopSettings(threshold_folds=2))
    assert folds_continue(on, next_rounds=True)
    assert not folds_continue(on, next_rounds=False)  # nothing to go on from
    offs = [{"threshold_folds": 0}, {"class_thresholds": False}, {"round_epochs": 0}]
    offs.append({"continue_folds": False})
    for off in offs:
        assert not folds_continue({**on, **off}, next_rounds=True), off
    # A record from before the setting existed fitted its folds afresh every round.
    old_record = {k: v for k, v in on.items() if k != "continue_folds"}
    assert not folds_continue(old_record, next_rounds=True)


@given(st.data())
def test_loop_arguments_give_back_the_settings_they_were_made_from(data):
    from factorydet_core.cli import build_parser, loop_settings_from_args

    values = {}
    controls = st.lists(st.sampled_from(LOOP_CONTROLS), max_size=6, unique_by=lambda c: c.field)
    for control in data.draw(controls):
        if control.kind is bool:
            values[control.field] = not control.default
        elif control.choices is not None:
            values[control.field] = data.draw(st.sampled_from([text for text, _ in control.choices]))
        else:
            step = control.step or 1
            low, high = control.minimum, min(control.maximum, control.minimum + 20 * step)
            number = data.draw(st.integers(0, int((high - low) / step))) * step + low
            values[control.field] = int(round(number)) if control.kind is int else round(number, 6)
    try:
        settings = loop_settings_from(values)
    except InputError:  # a combination the settings refuse (e.g. head_options without box quality)
        assume(False)
    args = build_parser().parse_args(["train", "--session", "s", *loop_arguments(settings)])
    assert loop_settings_from_args(args) == settings


def test_loop_arguments_refuse_a_value_no_flag_gives():
    with pytest.raises(InputError, match="no command-line flag"):
        loop_arguments(dataclasses.replace(LoopSettings(), mining_threshold=None))
