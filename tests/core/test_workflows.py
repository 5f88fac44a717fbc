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
        progress=lambda what, k, n: seen.append(what),
    )  # fmt: skip
    assert done.run_id == db.latest_run_id() and done.detector.params == front_end
    assert [f.frame_index for f in done.train_frames] == dataset.splits["train"][:2]
    assert set(done.comparison) == {"shipped", f"run {done.run_id}"}
    assert db.training_runs()[-1]["metrics"]["compare"] == done.comparison
    stored = DetectionModel.load(db.session.path / db.training_runs()[-1]["model_path"])
    assert stored.front_end == front_end  # carried whole into the checkpoint
    assert {"proposals", "fit", "compare"} <= set(seen)
