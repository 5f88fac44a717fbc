"""The per-frame work of the batch commands, as jobs ``runner.run_frames`` runs anywhere.

A job holds only paths and small arrays until ``setup`` (it travels to Ray workers by pickle) and
writes one ``.npz`` per frame (``runner.frame_path``).
"""

from __future__ import annotations

import contextlib
import dataclasses
import fcntl
import hashlib
import itertools
import json
import os
import shutil
import tempfile
from collections.abc import Callable, Iterator, Sequence
from pathlib import Path

import numpy as np

from factorydet_core.detection.detector import Detector, params_for
from factorydet_core.detection.model import DetectionModel
from factorydet_core.io.dataset import Dataset, open_dataset
from factorydet_core.io.npz import load_npz, save_npz
from factorydet_core.proposals.settings import FrontEndParams
from factorydet_core.scale.runner import BatchRun, Execution, SetUpOnce, frame_path, run_frames
from factorydet_core.sim.simulate import FactorySimulator, SimConfig, finish_dataset, write_frame
from factorydet_core.training.loop import Proposer, proposals_cache_key
from factorydet_core.training.mining import (
    FrameProposals,
    Progress,
    Scorer,
    collect_proposals,
    kept_detections,
    proposals_from_arrays,
    proposals_to_arrays,
    score_frames,
    scored_frame,
)
from factorydet_core.types import Cancelled, Detections, InputError

DETECTION_KEYS = ("boxes", "class_ids", "scores", "suppressed_by", "probabilities")
"""What a detect job writes per frame: ``types.Detections``' arrays (vehicle frame), NMS-suppressed
ones included with the index of the detection that suppressed them (-1: kept)."""


def _array_digest(array: np.ndarray | None) -> str | None:
    """SHA-256 of an array rounded to 6 decimals (extrinsics in a job's description: an ICP that
    differs in the last bits between runs is the same calibration); ``None`` for none."""
    if array is None:
        return None
    rounded = np.round(np.asarray(array, np.float64), 6) + 0.0  # + 0.0: -0.0 and 0.0 alike
    return hashlib.sha256(np.ascontiguousarray(rounded).tobytes()).hexdigest()


def data_identity(path: str) -> dict:
    """A data set in a job's description: its path and the SHA-256 of its manifest (of the file
    itself for a single point-cloud file), so that a data set simulated anew at the same path is
    another job's input, not frames to resume."""
    source = Path(path)
    manifest = source / "manifest.json" if source.is_dir() else source
    return {"data": str(source), "data_sha256": file_digest(manifest) if manifest.is_file() else None}


def file_digest(path: str | os.PathLike) -> str:
    """SHA-256 of a file (a model's identity in a batch job's description)."""
    digest = hashlib.sha256()
    with open(path, "rb") as handle:
        for chunk in iter(lambda: handle.read(1 << 20), b""):
            digest.update(chunk)
    return digest.hexdigest()


@dataclasses.dataclass
class ModelJob(SetUpOnce):
    """A frame job of one model on one data set (``DetectJob``, ``evaluate.EvaluateJob``).

    Args:
        data: the data set folder (every worker must see it at this path).
        model_path: the checkpoint (the same).
        T_vehicle_sensor: (S, 4, 4) extrinsics to merge with, calibrated once by the caller
            (``evaluate.detector_for``); ``None``: each frame's own.
    """

    data: str
    model_path: str
    T_vehicle_sensor: np.ndarray | None = None

    def __post_init__(self) -> None:
        # Absolute: a worker's working folder is not the driver's.
        self.data = str(Path(self.data).resolve())
        self.model_path = str(Path(self.model_path).resolve())

    def model_identity(self) -> dict:
        """The data, the model and the extrinsics, by content (part of ``describe``)."""
        return {
            **data_identity(self.data),
            "model_sha256": file_digest(self.model_path),
            "T_vehicle_sensor_sha256": _array_digest(self.T_vehicle_sensor),
        }

    def open_model(self) -> tuple[Dataset, DetectionModel, Detector]:
        """The data set, the model (its classes checked against the data's) and its detector."""
        dataset = open_dataset(self.data)
        model = DetectionModel.load(self.model_path)
        model.check_classes(dataset.class_names)
        return dataset, model, Detector(params_for(model, dataset.num_sensors), self.T_vehicle_sensor, model)


@dataclasses.dataclass
class DetectJob(ModelJob):
    """Detect every frame with one model: the front half, the box head, the score threshold, NMS.

    Args:
        data, model_path, T_vehicle_sensor: as ``ModelJob``'s.
        score_threshold, nms_iou: the operating point; ``None``: the model's (with its per-class
            thresholds).
    """

    score_threshold: float | None = None
    nms_iou: float | None = None
    kind: str = "detect"

    def describe(self) -> dict:
        return {**self.model_identity(), "score_threshold": self.score_threshold, "nms_iou": self.nms_iou}

    def load(self) -> tuple[Dataset, Detector]:
        dataset, _, detector = self.open_model()
        return dataset, detector

    def run(self, frame_index: int, out_path: Path) -> dict[str, float]:
        dataset, detector = self.loaded()
        result = detector.detect(
            dataset.frame(frame_index),
            detector.history(dataset, frame_index),
            score_threshold=self.score_threshold,
            nms_iou=self.nms_iou,
        )
        detections = result.detections
        save_npz(out_path, {key: getattr(detections, key) for key in DETECTION_KEYS})
        return {
            "num_detections": int(detections.kept_mask.sum()),
            "num_suppressed": int((~detections.kept_mask).sum()),
            "total_ms": float(result.timings_ms["total"]),
        }


def read_detections(path: str | os.PathLike) -> dict[str, np.ndarray]:
    """A detect job's frame file: ``DETECTION_KEYS`` -> arrays."""
    _, arrays = load_npz(path, DETECTION_KEYS)
    missing = [k for k in DETECTION_KEYS if k not in arrays]
    if missing:
        raise InputError(f"{path}: not a detection file (missing {', '.join(missing)})")
    return arrays


@dataclasses.dataclass
class SimulateJob(SetUpOnce):
    """Render simulated frames into a data set folder (``sim.simulate.write_frame``): a frame's
    bytes depend on the config and its index alone, so workers may render any frames in any order."""

    out: str
    config: SimConfig
    kind: str = "simulate"

    def __post_init__(self) -> None:
        self.out = str(Path(self.out).resolve())

    def describe(self) -> dict:
        return {"config": dataclasses.asdict(self.config)}

    def load(self) -> FactorySimulator:
        (Path(self.out) / "truth").mkdir(parents=True, exist_ok=True)
        return FactorySimulator(self.config)

    def run(self, frame_index: int, out_path: Path) -> dict[str, float]:
        written = write_frame(Path(self.out), self.loaded(), frame_index)
        if written != out_path:  # the runner's layout is the data set's: frames/frame_NNNNN.npz
            raise RuntimeError(f"frame written to {written}, expected {out_path}")
        return {"bytes": float(written.stat().st_size)}


def simulate_batch(
    out_dir: str | os.PathLike,
    config: SimConfig,
    execution: Execution,
    progress: Callable[[int, int], None] | None = None,
) -> BatchRun:
    """``sim.simulate.simulate_dataset`` with the frames rendered by ``execution`` (Ray workers);
    the same config gives the same files. A re-run finishes an interrupted one."""
    out = Path(out_dir)
    run = run_frames(SimulateJob(str(out), config), range(config.num_frames), out, execution, progress)
    finish_dataset(out, FactorySimulator(config))
    return run


@dataclasses.dataclass
class ProposeJob(SetUpOnce):
    """The front half of training frames (``training.mining.collect_proposals``: proposals, point
    sets, the annotations' samples), one cache-format file per frame
    (``training.mining.proposals_to_arrays``)."""

    data: str
    params: FrontEndParams
    T_vehicle_sensor: np.ndarray | None = None
    kind: str = "propose"

    def __post_init__(self) -> None:
        self.data = str(Path(self.data).resolve())

    def describe(self) -> dict:
        return {
            **data_identity(self.data),
            "params": json.loads(json.dumps(dataclasses.asdict(self.params), default=str)),
            "T_vehicle_sensor_sha256": _array_digest(self.T_vehicle_sensor),
        }

    def load(self) -> tuple[Dataset, Detector]:
        return open_dataset(self.data), Detector(self.params, self.T_vehicle_sensor)

    def run(self, frame_index: int, out_path: Path) -> dict[str, float]:
        dataset, detector = self.loaded()
        (frame,) = collect_proposals(dataset, [frame_index], detector)
        save_npz(out_path, proposals_to_arrays([frame]))
        return {"num_proposals": len(frame.proposal_boxes)}


def propose_batch(
    dataset: Dataset,
    frame_indices: Sequence[int],
    detector: Detector,
    execution: Execution,
    progress: Progress | None = None,
) -> list[FrameProposals]:
    """``collect_proposals`` run by ``execution`` (Ray workers): the frames travel through files in
    a folder under ``execution.scratch`` (default: ``$TMPDIR``), which every node of a cluster must
    see. The folder is named as the session's proposals cache names these proposals (data set
    content, front half, extrinsics, cache format), so that an interrupted run (a training
    cancelled, a driver killed) is resumed by the next that proposes them; it is removed once they
    are read back. A run that finds the folder in use by another one proposes into a folder of its
    own."""
    job = ProposeJob(str(dataset.path), detector.params, detector.T_vehicle_sensor)
    frames = [int(i) for i in frame_indices]
    report = None if progress is None else (lambda done, total: progress("proposals", done, total))
    with resumable_folder(execution, proposals_cache_key(dataset, detector)) as out:
        run_frames(job, frames, out, execution, report)
        proposed = [proposals_from_arrays(load_npz(frame_path(out, i))[1])[0] for i in frames]
        shutil.rmtree(out, ignore_errors=True)
    return proposed


@contextlib.contextmanager
def resumable_folder(execution: Execution, name: str) -> Iterator[Path]:
    """The folder ``name`` for a batch job's frames, in this user's own folder under
    ``execution.scratch`` (``$TMPDIR`` by default): the same for the same job, so that a re-run
    finds what an interrupted one computed. Held under an exclusive lock while in use; when another
    process holds it, a temporary folder of this run's own is given instead (nothing resumed,
    nothing shared).

    Raises:
        InputError: no scratch folder, or this user's folder in it belongs to someone else.
    """
    root = Path(execution.scratch) if execution.scratch is not None else Path(tempfile.gettempdir())
    if not root.is_dir():
        raise InputError(f"the scratch folder {root} does not exist")
    # Per user, private: in a shared $TMPDIR nobody else can plant frames for this run to read.
    mine = root / f"factorydet-{os.getuid()}"
    mine.mkdir(mode=0o700, exist_ok=True)
    if mine.is_symlink() or mine.stat().st_uid != os.getuid():
        raise InputError(f"{mine} is not this user's folder; remove it or give --scratch")
    with open(mine / f"{name}.lock", "a") as lock:
        try:
            fcntl.flock(lock, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:  # another run proposes the same frames right now
            with tempfile.TemporaryDirectory(prefix=f"{name}-", dir=mine) as own:
                yield Path(own)
            return
        try:
            yield mine / name
        finally:
            fcntl.flock(lock, fcntl.LOCK_UN)


def proposer(execution: Execution | None) -> Proposer:
    """What ``training.loop.cached_proposals`` proposes the frames its cache lacks with: on Ray
    workers when ``execution`` says so (``propose_batch``), else ``collect_proposals`` here."""
    if execution is None or not execution.uses_ray:
        return collect_proposals

    def propose(
        dataset: Dataset, frame_indices: Sequence[int], detector: Detector, progress: Progress | None = None
    ) -> list[FrameProposals]:
        return propose_batch(dataset, frame_indices, detector, execution, progress)

    return propose


SCORE_KEYS = ("boxes", "class_ids", "scores", "probabilities", "proposal_ids", "suppressed_by")
"""What a score job writes per frame: the kept detections' arrays (``types.Detections``)."""


@dataclasses.dataclass
class ScoreJob(SetUpOnce):
    """A mining round's per-frame work (``training.mining.score_frames``): one model's detections
    of a training frame down to the mining floor, from the frame's proposals in ``proposals_dir``
    (``frame_path`` layout, ``training.mining.proposals_to_arrays``' format)."""

    model_path: str
    proposals_dir: str
    score_threshold: float
    kind: str = "score"

    def __post_init__(self) -> None:
        self.model_path = str(Path(self.model_path).resolve())
        self.proposals_dir = str(Path(self.proposals_dir).resolve())

    def describe(self) -> dict:
        return {
            "model_sha256": file_digest(self.model_path),
            "proposals": self.proposals_dir,
            "score_threshold": self.score_threshold,
        }

    def load(self) -> DetectionModel:
        return DetectionModel.load(self.model_path)

    def run(self, frame_index: int, out_path: Path) -> dict[str, float]:
        (frame,) = proposals_from_arrays(load_npz(frame_path(self.proposals_dir, frame_index))[1])
        kept = kept_detections(self.loaded(), frame, self.score_threshold)
        save_npz(out_path, {key: getattr(kept, key) for key in SCORE_KEYS})
        return {"num_detections": len(kept.boxes)}


def batch_scorer(execution: Execution, folder: Path) -> Scorer:
    """A ``Scorer`` that runs ``ScoreJob`` as ``execution`` says (Ray workers; in this process for
    tests) through files in ``folder``:
    the frames' proposals written once (the first round), each round's model saved, each round's
    detections read back and removed."""
    written: set[int] = set()
    rounds = itertools.count()

    def score(
        model: DetectionModel,
        frames: list[FrameProposals],
        score_threshold: float,
        progress: Progress | None = None,
        should_stop: Callable[[], bool] | None = None,
    ) -> list[dict]:
        round_dir = folder / f"round_{next(rounds)}"
        try:
            model_path = model.save(round_dir / "model.pt")
        except InputError:  # a classifier without checkpoints (a baseline): scored here
            return score_frames(model, frames, score_threshold, progress, should_stop)
        proposals_dir = folder / "proposals"
        frame_path(proposals_dir, 0).parent.mkdir(parents=True, exist_ok=True)
        for frame in frames:
            if frame.frame_index not in written:
                save_npz(frame_path(proposals_dir, frame.frame_index), proposals_to_arrays([frame]))
                written.add(frame.frame_index)

        def report(done: int, total: int) -> None:
            if should_stop is not None and should_stop():
                raise Cancelled("training cancelled")  # stops the Ray run (``run_frames``)
            if progress is not None:
                progress("score", done, total)

        out = round_dir / "detections"
        job = ScoreJob(str(model_path), str(proposals_dir), float(score_threshold))
        run_frames(job, [f.frame_index for f in frames], out, execution, report)
        scored = []
        for frame in frames:
            arrays = load_npz(frame_path(out, frame.frame_index), SCORE_KEYS)[1]
            scored.append(scored_frame(frame, Detections(**arrays, class_names=model.class_names)))
        shutil.rmtree(round_dir)
        return scored

    return score


@contextlib.contextmanager
def scoring(execution: Execution | None) -> Iterator[Scorer]:
    """What scores a training run's mining rounds (``training.mining.train_with_mining``'s
    ``score``): ``score_frames`` in this process, or, when ``execution`` says so, Ray workers that
    load each round's model once and score the frames it hands them (the frames and the models
    travel through a temporary folder under ``execution.scratch``, removed on exit). The fits run
    in this process either way: they need every frame at once."""
    if execution is None or not execution.uses_ray:
        yield score_frames
        return
    with execution.scratch_folder("factorydet-scores-") as folder:
        yield batch_scorer(execution, Path(folder))
