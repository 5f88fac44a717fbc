import json

import numpy as np
import pytest
import torch

from factorydet_core.detection.classifier import (
    BACKGROUND,
    FisherNet,
    ProposalClassifier,
    class_weights,
    count_parameters,
)
from factorydet_core.detection.groups import DESCRIPTOR_NAMES
from factorydet_core.types import InputError


def _blobs(rng, num_per_class: int, num_labels: int = 3) -> tuple[np.ndarray, np.ndarray]:
    """Features whose class shows as a bright Gaussian cell, plus noise."""
    features = rng.normal(0, 0.3, (num_per_class * num_labels, 20, 5, 5, 5)).astype(np.float32)
    labels = np.repeat(np.arange(num_labels), num_per_class)
    for c in range(num_labels):
        features[labels == c, :, c, 2, 2] += 2.0
    return features, labels


def test_full_width_is_the_papers_size_and_narrow_is_small():
    assert 45_000_000 < count_parameters(FisherNet(8, 1.0)) < 46_500_000
    narrow = FisherNet(8, 0.0625)
    assert count_parameters(narrow) < 300_000
    narrow.eval()
    assert narrow(torch.zeros(2, 20, 5, 5, 5)).shape == (2, 8)


@pytest.mark.slow
def test_fit_learns_a_separable_problem_and_returns_self(rng):
    features, labels = _blobs(rng, 40)
    test_features, test_labels = _blobs(np.random.default_rng(1), 20)
    model = ProposalClassifier(
        width=0.0625, epochs=25, learning_rate=3e-3, class_names=("a", "b"), num_threads=1, geometry=False
    )
    assert model.fit(features, labels) is model
    assert model.labels_ == ("a", "b", BACKGROUND)
    proba = model.predict_proba(test_features)
    np.testing.assert_allclose(proba.sum(axis=1), 1.0, atol=1e-5)
    assert (model.predict(test_features) == test_labels).mean() > 0.9
    assert len(model.history_) == 25 and model.history_[-1]["loss"] < model.history_[0]["loss"]


def test_checkpoint_round_trip(rng, tmp_path):
    features, labels = _blobs(rng, 10)
    model = ProposalClassifier(width=0.0625, epochs=1, class_names=("a", "b"), geometry=False)
    model.fit(features, labels)
    path = model.save(tmp_path / "m.pt", {"metrics": {"f1": 0.5}})
    loaded = ProposalClassifier.load(path)
    np.testing.assert_allclose(loaded.predict_proba(features), model.predict_proba(features), atol=1e-6)
    assert loaded.note_["metrics"] == {"f1": 0.5}
    assert loaded.note_["train_hash"] == model.train_hash_
    assert loaded.class_names == ("a", "b")
    with pytest.raises(InputError):
        ProposalClassifier.load(tmp_path / "missing.pt")
    (tmp_path / "bad.pt").write_bytes(b"not a checkpoint")
    (tmp_path / "bad.json").write_text((tmp_path / "m.json").read_text())
    with pytest.raises(InputError):
        ProposalClassifier.load(tmp_path / "bad.pt")


def test_bad_inputs_raise(rng):
    model = ProposalClassifier(width=0.0625, epochs=1, geometry=False)
    with pytest.raises(InputError):
        model.predict_proba(np.zeros((1, 20, 5, 5, 5), np.float32))  # not fitted
    with pytest.raises(InputError):
        model.fit(np.zeros((4, 20, 4, 4, 4)), np.zeros(4))
    with pytest.raises(InputError):
        model.fit(np.zeros((4, 20, 5, 5, 5)), np.full(4, 99))
    bad = np.zeros((4, 20, 5, 5, 5))
    bad[0, 0, 0, 0, 0] = np.nan
    with pytest.raises(InputError):
        model.fit(bad, np.zeros(4))
    with pytest.raises(InputError):
        ProposalClassifier(width=0)
    with pytest.raises(InputError):
        ProposalClassifier(class_weight="heavy")


def test_class_weights_balanced_sqrt_and_none():
    counts = np.array([100.0, 400.0, 0.0, 1600.0])
    assert class_weights(counts, None) is None
    balanced = class_weights(counts, "balanced").numpy()
    sqrt = class_weights(counts, "sqrt").numpy()
    for w in (balanced, sqrt):
        assert w[2] == 0.0
        assert (w * counts).sum() == pytest.approx(counts.sum(), rel=1e-5)  # mean weight 1 per sample
    # Balanced: every present class weighs the same in total; sqrt: rare classes still weigh more
    # per sample, by the square root of the frequency ratio.
    np.testing.assert_allclose((balanced * counts)[[0, 1, 3]], counts.sum() / 3, rtol=1e-5)
    assert sqrt[0] / sqrt[3] == pytest.approx(4.0, rel=1e-5)
    assert balanced[0] / balanced[3] == pytest.approx(16.0, rel=1e-5)


def _sized(rng, num_per_class: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Noise features that carry no class; the class shows only in the height descriptor."""
    features = rng.normal(0, 0.3, (2 * num_per_class, 20, 5, 5, 5)).astype(np.float32)
    labels = np.repeat([0, 1], num_per_class)
    descriptors = rng.normal(0, 0.05, (2 * num_per_class, len(DESCRIPTOR_NAMES))).astype(np.float32)
    descriptors[:, DESCRIPTOR_NAMES.index("height_m")] += np.where(labels == 0, 0.5, 2.0)
    return features, descriptors, labels


@pytest.mark.slow
def test_geometry_learns_what_only_the_descriptors_tell(rng, tmp_path):
    """Classes told apart by size alone: only the network that reads the descriptors learns it,
    and its standardisation of them survives a checkpoint."""
    features, descriptors, labels = _sized(rng, 150)
    test_features, test_descriptors, test_labels = _sized(np.random.default_rng(1), 40)
    settings = dict(width=0.0625, epochs=20, learning_rate=3e-3, class_names=("a",), num_threads=1)
    with_geometry = ProposalClassifier(**settings).fit(features, labels, descriptors)
    assert with_geometry.input_kind == "features+descriptors"
    assert (with_geometry.predict(test_features, test_descriptors) == test_labels).mean() > 0.95
    without = ProposalClassifier(**settings, geometry=False).fit(features, labels)
    assert without.input_kind == "features"
    assert (without.predict(test_features) == test_labels).mean() < 0.75
    loaded = ProposalClassifier.load(with_geometry.save(tmp_path / "g.pt"))
    assert loaded.geometry
    np.testing.assert_allclose(
        loaded.predict_proba(test_features, test_descriptors),
        with_geometry.predict_proba(test_features, test_descriptors),
        atol=1e-6,
    )
    with pytest.raises(InputError, match="descriptors"):
        with_geometry.predict_proba(features)
    with pytest.raises(InputError, match="descriptors"):
        with_geometry.predict_proba(features, descriptors[:, :3])


def test_checkpoint_from_before_the_geometry_option_loads_as_the_papers_network(rng, tmp_path):
    features, labels = _blobs(rng, 10)
    model = ProposalClassifier(width=0.0625, epochs=1, class_names=("a", "b"), geometry=False)
    path = model.fit(features, labels).save(tmp_path / "old.pt")
    note = json.loads(path.with_suffix(".json").read_text())
    del note["params"]["geometry"]
    path.with_suffix(".json").write_text(json.dumps(note))
    loaded = ProposalClassifier.load(path)
    assert not loaded.geometry
    np.testing.assert_allclose(loaded.predict_proba(features), model.predict_proba(features), atol=1e-6)


def test_the_shipped_paper_checkpoint_loads():
    from factorydet_core.detection.model import PAPER_MODEL

    model = ProposalClassifier.load(PAPER_MODEL)
    features = np.zeros((2, 20, 5, 5, 5), np.float32)
    descriptors = np.ones((2, len(DESCRIPTOR_NAMES)), np.float32)
    proba = model.predict_proba(features, descriptors if model.geometry else None)
    np.testing.assert_allclose(proba.sum(axis=1), 1.0, atol=1e-5)


def test_a_fit_goes_on_from_a_fitted_classifier_and_leaves_it_as_it_was(rng):
    features, labels = _blobs(rng, 10)
    kwargs = {"width": 0.0625, "class_names": ("a", "b"), "num_threads": 1, "geometry": False}
    first = ProposalClassifier(epochs=1, **kwargs).fit(features, labels)
    before = {k: v.clone() for k, v in first.network_.state_dict().items()}
    start = ProposalClassifier(epochs=1, max_fit_seconds=1e-9, **kwargs)
    start.fit(features, labels, init_model=first)
    assert all(torch.equal(v, before[k]) for k, v in start.network_.state_dict().items())
    np.testing.assert_allclose(start.predict_proba(features), first.predict_proba(features), atol=1e-6)
    tuned = ProposalClassifier(epochs=1, **kwargs).fit(features, labels, init_model=first)
    assert any(not torch.equal(v, before[k]) for k, v in tuned.network_.state_dict().items())
    assert all(torch.equal(v, before[k]) for k, v in first.network_.state_dict().items())
    with pytest.raises(InputError, match="width"):
        ProposalClassifier(epochs=1, **{**kwargs, "width": 0.125}).fit(features, labels, init_model=first)
