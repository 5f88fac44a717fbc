import pytest

from factorydet_core.detection.model import DetectionModel
from factorydet_core.io.dataset import open_dataset
from factorydet_core.proposals.settings import PRESETS
from factorydet_core.session.store import SessionDB, open_session
from factorydet_core.training.settings import LoopSettings
from factorydet_core.types import InputError
from factorydet_core.workflows import retrain_session

TINY = LoopSettings(
    epochs=1, rounds=0, initial_negatives=100, negatives_per_round=20, box_quality=False, method="paper"
)


@pytest.mark.slow
def test_retrain_stores_the_run_its_settings_and_the_before_after_table(
    small_dataset_dir, tiny_model_path, tmp_path
):
    dataset = open_dataset(small_dataset_dir)
    db = SessionDB(open_session("s", tmp_path), dataset)
    with pytest.raises(InputError, match="no training run to continue"):
        retrain_session(db, dataset, TINY, PRESETS["agv"], mode="next")
    front_end = PRESETS["agv"].replace(min_proposal_points=40)
    seen = []
    done = retrain_session(
        db, dataset, TINY, front_end, mode="full", calibrate=False,
        before={"shipped": DetectionModel.load(tiny_model_path)}, max_train_frames=2,
        progress=lambda what, k, n: seen.append((what, k, n)),
    )  # fmt: skip
    assert done.run_id == db.latest_run_id() and done.detector.params == front_end
    assert [f.frame_index for f in done.train_frames] == dataset.splits["train"][:2]
    assert set(done.comparison) == {"shipped", f"run {done.run_id}"}
    assert db.training_runs()[-1]["metrics"]["compare"] == done.comparison
    stored = DetectionModel.load(db.session.path / db.training_runs()[-1]["model_path"])
    assert stored.front_end == front_end  # carried whole into the checkpoint
    assert {"proposals", "fit", "compare"} <= {what for what, _, _ in seen}
    # The comparison reports the test frames it proposes (none cached yet), one by one.
    num_test = len(dataset.splits["test"])
    assert [(k, n) for what, k, n in seen if what == "compare"] == [(0, 1)] + [
        (k, num_test) for k in range(1, num_test + 1)
    ]


def test_a_next_round_that_carries_pseudo_labels_places_the_world_unless_given_one(
    small_dataset_dir, tiny_model_path, tmp_path, monkeypatch
):
    from factorydet_core import workflows
    from tests.fakes import queue_run

    dataset = open_dataset(small_dataset_dir)
    db = SessionDB(open_session("s", tmp_path), dataset)
    db.save_training_run(queue_run(tiny_model_path, [[]]), "small", {})
    placed, worlds = [], []
    monkeypatch.setattr(workflows, "cached_proposals", lambda *a, **k: [])
    monkeypatch.setattr(
        workflows,
        "session_world",
        lambda session, data, progress: placed.append(progress) or ("placed", False),
    )

    def train_session(db, frames, settings, **options):
        worlds.append(options["world"])
        raise RuntimeError("stop here")

    monkeypatch.setattr(workflows, "train_session", train_session)
    carry = LoopSettings(pseudo_label_confident=0.6, carry_pseudo_labels=True)
    seen = []
    for settings, mode, world in (
        (carry, "next", None),
        (carry, "next", "given"),
        (carry, "full", None),  # a first fit has no pseudo-labels
        (LoopSettings(carry_pseudo_labels=True), "next", None),  # nothing to carry
    ):
        with pytest.raises(RuntimeError, match="stop here"):
            retrain_session(
                db, dataset, settings, PRESETS["agv"], mode=mode, calibrate=False, world=world,
                progress=lambda what, k, n: seen.append((what, k, n)),
            )  # fmt: skip
    assert worlds == ["placed", "given", None, None] and len(placed) == 1
    placed[0](1, 3)
    assert seen[-1] == ("world", 1, 3)  # its progress is reported as the run's
