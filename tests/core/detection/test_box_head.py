import json

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from factorydet_core.boxes import box_iou_3d
from factorydet_core.detection.box_head import (
    BoxHead,
    HeadSamples,
    _augment,
    canonical_frame,
    decode_boxes,
    encode_boxes,
    head_candidates,
    label_point_sets,
    paired_iou,
    share_inside,
    symmetry_orders,
    to_canonical,
)
from factorydet_core.detection.groups import DESCRIPTOR_NAMES, ProposalGroups
from factorydet_core.types import InputError

TEMPLATES = np.array([[0.6, 0.6, 0.9], [1.2, 0.8, 0.15], [3.5, 1.2, 2.2]])
"""A round class, a flat rectangle and a long one."""
SYMMETRY = symmetry_orders(TEMPLATES)


def _boxes(rng, num: int, class_ids: np.ndarray) -> np.ndarray:
    centres = np.column_stack([rng.uniform(-20, 20, (num, 2)), rng.uniform(0, 3, num)])
    sizes = TEMPLATES[class_ids] * rng.uniform(0.7, 1.3, (num, 3))
    square = SYMMETRY[class_ids] == 4
    sizes[square, 1] = sizes[square, 0]
    return np.column_stack([centres, sizes, rng.uniform(-np.pi, np.pi, num)])


def test_square_templates_have_quarter_turn_symmetry():
    assert SYMMETRY.tolist() == [4, 2, 2]


box_strategy = st.tuples(
    st.floats(-30, 30), st.floats(-30, 30), st.floats(-1, 4),
    st.floats(0.1, 4), st.floats(0.1, 4), st.floats(0.1, 3), st.floats(-np.pi, np.pi),
    st.floats(-30, 30), st.floats(-30, 30), st.floats(0.2, 3), st.floats(0.2, 3), st.floats(-np.pi, np.pi),
    st.sampled_from([1, 2]),
)  # fmt: skip


@settings(max_examples=200, deadline=None)
@given(box_strategy)
def test_a_box_encoded_then_decoded_is_itself(values):
    """Any rectangle, in any set's frame: the decoded box covers the same space (IoU 1)."""
    *box, ax, ay, adx, ady, ayaw, class_id = values
    boxes = np.array([box], np.float64)
    anchors = np.array([[ax, ay, 0.5, adx, ady, 1.0, ayaw]])
    class_ids = np.array([class_id])
    origin, heading = canonical_frame(anchors)
    encoded = encode_boxes(boxes, origin, heading, class_ids, TEMPLATES, SYMMETRY, 12)
    assert 0 <= encoded.heading_bin[0] < 12 and -0.5 <= encoded.heading_residual[0] < 0.5 + 1e-9
    decoded = decode_boxes(encoded, origin, heading, class_ids, TEMPLATES, SYMMETRY, 12)
    assert paired_iou(decoded, boxes)[0] == pytest.approx(1.0, abs=1e-6)
    assert decoded[0, 3] >= decoded[0, 4] - 1e-9  # length along the heading


@settings(max_examples=100, deadline=None)
@given(st.floats(-np.pi, np.pi), st.integers(0, 3), st.floats(0.3, 1.0))
def test_square_footprints_encode_the_same_at_every_quarter_turn(yaw, quarter, side):
    """A round class's box turned by a quarter turn is the same box, and so the same target."""
    box = np.array([[3.0, -2.0, 0.45, side, side, 0.9, yaw]])
    turned = box.copy()
    turned[0, 6] += quarter * np.pi / 2
    anchors = np.array([[3.1, -2.1, 0.4, 0.5, 0.4, 0.8, 0.2]])
    origin, heading = canonical_frame(anchors)
    a = encode_boxes(box, origin, heading, np.array([0]), TEMPLATES, SYMMETRY, 12)
    b = encode_boxes(turned, origin, heading, np.array([0]), TEMPLATES, SYMMETRY, 12)
    angle_a = a.heading_bin + a.heading_residual
    angle_b = b.heading_bin + b.heading_residual
    assert np.abs((angle_a - angle_b + 6) % 12 - 6) < 1e-6  # the same folded heading
    np.testing.assert_allclose(a.centre, b.centre)


def test_a_rectangle_and_its_half_turn_encode_the_same(rng):
    class_ids = np.full(50, 2)
    boxes = _boxes(rng, 50, class_ids)
    turned = boxes.copy()
    turned[:, 6] += np.pi
    anchors = boxes + rng.normal(0, 0.2, boxes.shape)
    origin, heading = canonical_frame(anchors)
    a = encode_boxes(boxes, origin, heading, class_ids, TEMPLATES, SYMMETRY, 12)
    b = encode_boxes(turned, origin, heading, class_ids, TEMPLATES, SYMMETRY, 12)
    angle_a, angle_b = a.heading_bin + a.heading_residual, b.heading_bin + b.heading_residual
    np.testing.assert_allclose(angle_a, angle_b, atol=1e-9)


def test_canonical_frame_puts_the_anchor_at_the_origin_along_its_longer_side():
    anchors = np.array([[5.0, 5.0, 1.0, 0.5, 2.0, 1.0, 0.3]])  # longer along its y axis
    origin, heading = canonical_frame(anchors)
    assert heading[0] == pytest.approx(0.3 + np.pi / 2)
    end = np.array([[[5.0 - np.sin(0.3), 5.0 + np.cos(0.3), 1.0]]])  # 1 m along the long side
    np.testing.assert_allclose(to_canonical(end, origin, heading)[0, 0], [1.0, 0.0, 0.0], atol=1e-12)


def test_paired_iou_matches_the_pairwise_iou(rng):
    a = _boxes(rng, 30, rng.integers(0, 3, 30))
    b = a + rng.normal(0, 0.2, a.shape)
    np.testing.assert_allclose(paired_iou(a, b), np.diag(box_iou_3d(a, b)), atol=1e-9)


def test_point_sets_are_labelled_by_where_their_points_lie():
    boxes = np.array([[0.0, 0.0, 0.5, 1.0, 1.0, 1.0, 0.0], [5.0, 0.0, 0.5, 1.0, 1.0, 1.0, 0.0]])
    inside = np.zeros((1, 10, 3)) + [0.1, 0.1, 0.5]
    half = np.concatenate([inside[:, :5], inside[:, :5] + [5.0, 0, 0]], axis=1)  # two objects
    mostly = np.concatenate([inside[:, :7], inside[:, :3] + [0, 3.0, 0]], axis=1)  # 70% in one
    far = inside + [0, 10.0, 0]
    points = np.concatenate([inside, half, mostly, far])
    np.testing.assert_allclose(share_inside(points, boxes)[:, 0], [1.0, 0.5, 0.7, 0.0])
    labels, owners = label_point_sets(points, boxes, np.array([3, 4]), background_id=7)
    assert labels.tolist() == [3, -1, -1, 7]  # in between: left out of training
    assert owners.tolist() == [0, -1, -1, -1]


def test_augmentation_moves_points_and_boxes_together(rng):
    """After the random turn, mirror and scale, the target box still holds the object's points."""
    box = np.array([4.0, 2.0, 0.5, 1.2, 0.6, 1.0, 0.4])
    local = rng.uniform(-0.5, 0.5, (64, 3)) * box[3:6]
    c, s = np.cos(box[6]), np.sin(box[6])
    points = np.column_stack(
        [box[0] + local[:, 0] * c - local[:, 1] * s, box[1] + local[:, 0] * s + local[:, 1] * c,
         box[2] + local[:, 2]]
    )[None].repeat(32, axis=0)  # fmt: skip
    anchors = np.repeat(box[None], 32, axis=0)
    targets = anchors.copy()
    targets[::2] = np.nan  # background rows keep no box
    moved, moved_anchors, moved_targets = _augment(rng, points.astype(np.float32), anchors, targets)
    assert moved.shape == points.shape and np.isnan(moved_targets[::2, :6]).all()
    shares = share_inside(moved[1::2], moved_targets[1::2], margin_m=0.05)
    assert np.diag(shares).min() == 1.0


def _toy_samples(rng, num_per_class: int) -> tuple[HeadSamples, np.ndarray]:
    """Objects of two classes (a small cube and a long bar) and background (a thin wall patch),
    their points on the visible faces."""
    templates = np.array([[0.6, 0.6, 0.6], [2.0, 0.5, 0.5]])
    points, anchors, labels, targets = [], [], [], []
    for label in (0, 1, 2):
        for _ in range(num_per_class):
            centre = np.array([rng.uniform(3, 10), rng.uniform(-5, 5), 0.3])
            yaw = rng.uniform(-np.pi, np.pi)
            dims = templates[label] if label < 2 else np.array([1.5, 0.02, 1.5])
            local = rng.uniform(-0.5, 0.5, (64, 3)) * dims
            c, s = np.cos(yaw), np.sin(yaw)
            world = np.column_stack(
                [centre[0] + local[:, 0] * c - local[:, 1] * s, centre[1] + local[:, 0] * s + local[:, 1] * c,
                 centre[2] + local[:, 2]]
            )  # fmt: skip
            box = np.concatenate([centre, dims, [yaw]])
            points.append(world)
            anchors.append(box + np.concatenate([rng.normal(0, 0.05, 3), [0, 0, 0, 0]]))
            labels.append(label)
            targets.append(box if label < 2 else np.full(7, np.nan))
    num = len(labels)
    anchors = np.array(anchors)
    # Descriptors of a scene whose floor is at z = 0: the fitted box's bottom above it.
    descriptors = np.zeros((num, len(DESCRIPTOR_NAMES)), np.float32)
    descriptors[:, DESCRIPTOR_NAMES.index("bottom_above_floor_m")] = anchors[:, 2] - anchors[:, 5] / 2
    samples = HeadSamples(
        points=np.array(points, np.float32),
        anchor_boxes=anchors,
        descriptors=descriptors,
        labels=np.array(labels),
        target_boxes=np.array(targets),
    )
    return samples, templates


def test_training_on_a_tiny_set_reduces_its_losses_and_returns_self(rng):
    samples, templates = _toy_samples(rng, 40)
    head = BoxHead(channels=(16, 32), hidden=32, epochs=12, batch_size=32, class_names=("cube", "bar"),
                   num_threads=1, seed=0)  # fmt: skip
    assert head.fit(samples, templates) is head
    first, last = head.history_[0], head.history_[-1]
    assert last["loss"] < first["loss"] and last["box"] < first["box"] and last["class"] < first["class"]
    out = head.predict(samples.points, samples.anchor_boxes, samples.descriptors)
    assert out.probabilities.shape == (120, 3)
    assert out.boxes.shape == (120, 2, 7) and out.iou.shape == (120, 2)
    np.testing.assert_allclose(out.probabilities.sum(axis=1), 1.0, atol=1e-5)
    assert (out.probabilities.argmax(axis=1) == samples.labels).mean() > 0.8
    assert ((out.iou >= 0) & (out.iou <= 1)).all()


def test_checkpoint_round_trip_loads_weights_only(rng, tmp_path, monkeypatch):
    samples, templates = _toy_samples(rng, 8)
    head = BoxHead(channels=(8,), hidden=8, epochs=1, batch_size=16, class_names=("cube", "bar"))
    head.fit(samples, templates)
    path = head.save(tmp_path / "head.pt", {"front_end": {"preset": "agv"}})
    assert json.loads(path.with_suffix(".json").read_text())["format"] == "factorydet-box-head/1"

    import torch

    calls = []
    real_load = torch.load

    def spy(*args, **kwargs):
        calls.append(kwargs.get("weights_only"))
        return real_load(*args, **kwargs)

    monkeypatch.setattr(torch, "load", spy)
    loaded = BoxHead.load(path)
    assert calls == [True]
    a = head.predict(samples.points, samples.anchor_boxes, samples.descriptors)
    b = loaded.predict(samples.points, samples.anchor_boxes, samples.descriptors)
    np.testing.assert_allclose(a.probabilities, b.probabilities, atol=1e-6)
    np.testing.assert_allclose(a.boxes, b.boxes, atol=1e-6)
    assert loaded.note_["front_end"] == {"preset": "agv"} and loaded.class_names == ("cube", "bar")
    np.testing.assert_array_equal(loaded.symmetry_, head.symmetry_)


def test_head_candidates_give_one_scored_box_per_point_set(rng):
    samples, templates = _toy_samples(rng, 6)
    head = BoxHead(channels=(8,), hidden=8, epochs=1, batch_size=16, class_names=("cube", "bar"))
    head.fit(samples, templates)
    num = samples.num_samples
    groups = ProposalGroups(
        group_ids=np.arange(num),
        representatives=np.arange(num),
        features=np.zeros((num, 20, 5, 5, 5), np.float32),
        descriptors=samples.descriptors,
        points=samples.points,
        fitted_boxes=samples.anchor_boxes,
    )
    candidates = head_candidates(groups, head, probability_exponent=0.5)
    out = head.predict(samples.points, samples.anchor_boxes, samples.descriptors)
    rows = np.arange(num)
    classes = out.probabilities[:, :2].argmax(axis=1)
    np.testing.assert_array_equal(candidates.class_ids, classes)
    np.testing.assert_allclose(
        candidates.scores, out.probabilities[rows, classes] ** 0.5 * out.iou[rows, classes], rtol=1e-5
    )
    np.testing.assert_allclose(candidates.boxes, out.boxes[rows, classes])
    without_points = ProposalGroups(
        groups.group_ids, groups.representatives, groups.features, groups.descriptors
    )
    with pytest.raises(InputError, match="points"):
        head_candidates(without_points, head)


def test_bad_inputs_are_refused(rng):
    samples, templates = _toy_samples(rng, 4)
    with pytest.raises(InputError):
        BoxHead(epochs=0)
    with pytest.raises(InputError, match="not fitted"):
        BoxHead().predict(samples.points, samples.anchor_boxes, samples.descriptors)
    no_objects = HeadSamples(
        samples.points, samples.anchor_boxes, samples.descriptors, np.full(samples.num_samples, 2),
        np.full((samples.num_samples, 7), np.nan),
    )  # fmt: skip
    with pytest.raises(InputError, match="at least one object"):
        BoxHead(class_names=("cube", "bar")).fit(no_objects, templates)
    with pytest.raises(InputError, match="shape"):
        HeadSamples(samples.points[:, :, :2], samples.anchor_boxes, samples.descriptors, samples.labels,
                    samples.target_boxes)  # fmt: skip


def test_corner_loss_is_zero_on_the_target_and_blind_to_its_symmetry(rng):
    import torch

    from factorydet_core.detection.box_head import _corner_loss

    class_ids = rng.integers(0, 3, 40)
    boxes = _boxes(rng, 40, class_ids)
    anchors = boxes + np.concatenate([rng.normal(0, 0.2, (40, 3)), np.zeros((40, 4))], axis=1)
    origin, heading = canonical_frame(anchors)
    encoded = encode_boxes(boxes, origin, heading, class_ids, TEMPLATES, SYMMETRY, 12)

    def loss(centre, log_size, residual):
        return float(
            _corner_loss(
                torch.tensor(centre, dtype=torch.float32), torch.tensor(log_size, dtype=torch.float32),
                torch.tensor(residual, dtype=torch.float32), encoded,
                torch.tensor(TEMPLATES[class_ids], dtype=torch.float32),
                torch.tensor(SYMMETRY[class_ids]), 12,
            )
        )  # fmt: skip

    exact = loss(encoded.centre, encoded.log_size, encoded.heading_residual)
    assert exact == pytest.approx(0.0, abs=1e-5)
    shifted = loss(encoded.centre + [0.1, 0, 0], encoded.log_size, encoded.heading_residual)
    assert shifted == pytest.approx(0.1, abs=1e-4)  # every corner 10 cm off
    assert loss(encoded.centre, encoded.log_size + 0.2, encoded.heading_residual) > 0.01
    # A whole turn of the folded heading (12 bins) is the box turned by its symmetry: no loss.
    assert loss(encoded.centre, encoded.log_size, encoded.heading_residual + 12) == pytest.approx(0, abs=1e-4)
    assert loss(encoded.centre, encoded.log_size, encoded.heading_residual + 3) > 0.05


def test_a_fit_goes_on_from_a_fitted_head_and_leaves_it_as_it_was(rng):
    import torch

    samples, templates = _toy_samples(rng, 8)
    kwargs = {"channels": (8,), "hidden": 8, "batch_size": 16, "class_names": ("cube", "bar"),
              "num_threads": 1}  # fmt: skip
    first = BoxHead(epochs=2, **kwargs).fit(samples, templates)
    before = {k: v.clone() for k, v in first.network_.state_dict().items()}
    # Out of time before its first step, a continued fit is its start (a copy of the weights).
    start = BoxHead(epochs=1, max_fit_seconds=1e-9, **kwargs).fit(samples, templates, init_model=first)
    assert all(torch.equal(v, before[k]) for k, v in start.network_.state_dict().items())
    assert start.network_ is not first.network_
    a = first.predict(samples.points, samples.anchor_boxes, samples.descriptors)
    b = start.predict(samples.points, samples.anchor_boxes, samples.descriptors)
    np.testing.assert_allclose(a.probabilities, b.probabilities, atol=1e-6)
    # An epoch from there moves the new weights and not the start's.
    tuned = BoxHead(epochs=1, **kwargs).fit(samples, templates, init_model=first)
    assert any(not torch.equal(v, before[k]) for k, v in tuned.network_.state_dict().items())
    assert all(torch.equal(v, before[k]) for k, v in first.network_.state_dict().items())
    # Another network, other classes or an unfitted head cannot be gone on from.
    with pytest.raises(InputError, match="channels"):
        BoxHead(epochs=1, **{**kwargs, "channels": (16,)}).fit(samples, templates, init_model=first)
    with pytest.raises(InputError, match="class_names"):
        swapped = BoxHead(epochs=1, **{**kwargs, "class_names": ("bar", "cube")})
        swapped.fit(samples, templates, init_model=first)
    with pytest.raises(InputError, match="fitted"):
        BoxHead(epochs=1, **kwargs).fit(samples, templates, init_model=BoxHead(**kwargs))


@pytest.mark.parametrize("epochs", [1, 2, 3, 10, 11])
def test_a_fit_of_a_few_steps_runs_its_learning_rate_schedule(rng, epochs):
    # One batch per epoch: torch's one-cycle schedule divided by zero at ten steps.
    samples, templates = _toy_samples(rng, 4)
    head = BoxHead(channels=(8,), hidden=8, epochs=epochs, batch_size=12, class_names=("cube", "bar"),
                   num_threads=1)  # fmt: skip
    assert len(head.fit(samples, templates).history_) == epochs


def test_background_recalibration_leaves_confident_drawn_background_out_of_the_loss(rng):
    import torch
    from torch import nn

    samples, templates = _toy_samples(rng, 6)
    head = BoxHead(channels=(8,), hidden=8, epochs=1, batch_size=64, class_names=("cube", "bar"),
                   num_threads=1, augment=False).fit(samples, templates)  # fmt: skip
    head.network_.eval()  # no dropout: the same sets give the same losses
    loss_fn = nn.CrossEntropyLoss(weight=torch.tensor([1.0, 2.0, 0.5]))
    every = np.arange(len(samples.labels))
    background = samples.labels == 2

    def step(batch, recalibrate=None, drawn=None, class_bars=None):
        with torch.no_grad():
            return head._step(head.network_, samples, batch, head.templates_, head.symmetry_, loss_fn,
                              np.random.default_rng(0), recalibrate=recalibrate, drawn=drawn,
                              class_bars=class_bars)  # fmt: skip

    plain = step(every)
    assert plain["recalibrated"] == 0
    # Every drawn background set left out (any object probability is >= 0): the losses are those
    # of the objects alone, weighted as the loss weighs them.
    left_out = step(every, recalibrate=0.0, drawn=np.ones(len(every), bool))
    objects = step(np.flatnonzero(~background))
    assert left_out["recalibrated"] == background.sum()
    torch.testing.assert_close(left_out["class"], objects["class"])
    torch.testing.assert_close(left_out["iou"] * len(every), objects["iou"] * (~background).sum())
    # Hard negatives (not drawn) are never left out, whatever the network thinks of them.
    hard = step(every, recalibrate=0.0, drawn=np.zeros(len(every), bool))
    assert hard["recalibrated"] == 0
    torch.testing.assert_close(hard["class"], plain["class"])
    # A threshold between the network's object probabilities leaves out the sets at or above it.
    object_probability = (
        1.0 - head.predict(samples.points, samples.anchor_boxes, samples.descriptors).probabilities[:, 2]
    )
    ranked = np.sort(object_probability[background])
    threshold = float(ranked[len(ranked) // 2 - 1] + ranked[len(ranked) // 2]) / 2
    some = step(every, recalibrate=threshold, drawn=None)  # None: every set was drawn
    assert 0 < some["recalibrated"] == (object_probability[background] >= threshold).sum() < background.sum()
    # Class bars: a set is left out only when its likeliest class's probability reaches that
    # class's bar too; bars of 0 change nothing, bars above 1 leave nothing out.
    probabilities = head.predict(samples.points, samples.anchor_boxes, samples.descriptors).probabilities
    assert step(every, recalibrate=threshold, class_bars=np.zeros(2))["recalibrated"] == some["recalibrated"]
    assert step(every, recalibrate=0.0, class_bars=np.full(2, np.inf))["recalibrated"] == 0
    likeliest = probabilities[:, :2].argmax(axis=1)
    bars = np.array([np.inf, float(np.median(probabilities[background & (likeliest == 1), 1]))])
    expected = background & (likeliest == 1) & (probabilities[:, 1] >= bars[1])
    by_class = step(every, recalibrate=0.0, class_bars=bars)
    assert 0 < by_class["recalibrated"] == expected.sum() < (background & (likeliest == 1)).sum()
    # The object sets' own-class probabilities, for the next bars.
    rows, own = plain["own_probability"]
    np.testing.assert_array_equal(rows, np.flatnonzero(~background))
    np.testing.assert_allclose(own, probabilities[rows, samples.labels[rows]], rtol=1e-5, atol=1e-6)
    # Without class weights, the kept sets' plain mean.
    loss_fn = nn.CrossEntropyLoss()
    torch.testing.assert_close(
        step(every, recalibrate=0.0, drawn=np.ones(len(every), bool))["class"],
        step(np.flatnonzero(~background))["class"],
    )


def test_background_recalibration_acts_only_in_a_fit_that_goes_on_from_a_head(rng):
    samples, templates = _toy_samples(rng, 10)
    kwargs = {"channels": (8,), "hidden": 8, "epochs": 2, "batch_size": 16, "class_names": ("cube", "bar"),
              "num_threads": 1, "seed": 0}  # fmt: skip
    # From scratch, a network's probabilities mean little yet: nothing is left out.
    first = BoxHead(**kwargs, recalibrate_background=0.01).fit(samples, templates)
    assert [epoch["recalibrated"] for epoch in first.history_] == [0, 0]
    # Going on from it, drawn background sets it finds at least 1% likely objects are left out.
    going_on = BoxHead(**kwargs, recalibrate_background=0.01).fit(samples, templates, init_model=first)
    assert sum(epoch["recalibrated"] for epoch in going_on.history_) > 0
    assert "recalibrated" not in BoxHead(**kwargs).fit(samples, templates).history_[0]
    with pytest.raises(InputError, match="recalibrate_background"):
        BoxHead(recalibrate_background=1.5)


def test_recalibrating_by_class_never_leaves_out_more_than_the_threshold_alone(rng):
    samples, templates = _toy_samples(rng, 10)
    kwargs = {"channels": (8,), "hidden": 8, "epochs": 2, "batch_size": 16, "class_names": ("cube", "bar"),
              "num_threads": 1, "seed": 0, "recalibrate_background": 0.01}  # fmt: skip
    first = BoxHead(**{**kwargs, "recalibrate_background": None}).fit(samples, templates)
    alone = BoxHead(**kwargs).fit(samples, templates, init_model=first)
    by_class = BoxHead(**kwargs, recalibrate_by_class=True).fit(samples, templates, init_model=first)
    # The same draws and the same first step; from there the networks part.
    left_out = [sum(e["recalibrated"] for e in head.history_) for head in (by_class, alone)]
    assert 0 < left_out[0] < left_out[1]
    # Saved and read back with the head's other settings.
    assert by_class.get_params()["recalibrate_by_class"] is True


def test_an_object_without_a_target_box_teaches_its_class_alone(rng):
    """An object set with a NaN target (its label's box is the model's own) counts in the class
    loss as before, and in neither the box nor the IoU loss: those are the other objects'."""
    import dataclasses

    import torch
    from torch import nn

    samples, templates = _toy_samples(rng, 6)
    head = BoxHead(channels=(8,), hidden=8, epochs=1, batch_size=64, class_names=("cube", "bar"),
                   num_threads=1, augment=False).fit(samples, templates)  # fmt: skip
    head.network_.eval()
    loss_fn = nn.CrossEntropyLoss()
    objects = np.flatnonzero(samples.labels < 2)
    no_box = objects[::2]
    targets = samples.target_boxes.copy()
    targets[no_box] = np.nan
    class_only = dataclasses.replace(samples, target_boxes=targets)

    def step(s, batch):
        with torch.no_grad():
            return head._step(head.network_, s, batch, head.templates_, head.symmetry_, loss_fn,
                              np.random.default_rng(0))  # fmt: skip

    every = np.arange(len(samples.labels))
    with_boxes, without = step(samples, every), step(class_only, every)
    torch.testing.assert_close(without["class"], with_boxes["class"])
    kept = np.setdiff1d(objects, no_box)
    torch.testing.assert_close(without["box"], step(samples, kept)["box"])
    assert not torch.isclose(without["box"], with_boxes["box"])
    # The IoU loss: the kept objects' and the background's terms, summed over the whole batch.
    background = np.flatnonzero(samples.labels == 2)
    expected_iou = (
        step(samples, kept)["iou"] * len(kept) + step(samples, background)["iou"] * len(background)
    ) / len(every)
    torch.testing.assert_close(without["iou"], expected_iou)
    # A fit on them runs; a target row partly NaN is refused.
    BoxHead(channels=(8,), hidden=8, epochs=1, batch_size=64, class_names=("cube", "bar"),
            num_threads=1).fit(class_only, templates)  # fmt: skip
    targets[objects[1], 3] = np.nan
    with pytest.raises(InputError, match="all NaN"):
        BoxHead(channels=(8,), hidden=8, epochs=1, class_names=("cube", "bar"), num_threads=1).fit(
            dataclasses.replace(samples, target_boxes=targets), templates
        )
