"""The background worker that runs the detector for the shown frame (the front half, and the
classifier and NMS when the app has a model).

Requests come from state changes (frame, parameters); only the latest matters, so a request that
arrives while a frame computes replaces any waiting one, and a result that is stale when it
finishes is dropped. The GUI thread never computes.
"""

from __future__ import annotations

import threading
import traceback

from factorydet_core.detection.detector import Detector

from .state import AppState


class PipelineWorker:
    """One daemon thread; ``request()`` asks for the state's current frame and parameters.

    Args:
        state: the app state (results and progress are written back into it).
        calibrate: refine the extrinsics by ICP once, before the first frame, when the data set has
            several sensors.
    """

    def __init__(self, state: AppState, calibrate: bool = True) -> None:
        self.state = state
        self.calibrate = calibrate
        self._refined_extrinsics = None
        self._pending = False
        self._stopped = False
        self._wake = threading.Condition()
        self._thread = threading.Thread(target=self._run, name="factorydet-pipeline", daemon=True)
        self._thread.start()

    def request(self) -> None:
        with self._wake:
            self._pending = True
            self._wake.notify()

    def maybe_request(self) -> None:
        """Request a run when the state's frame or parameters differ from the last result's (and
        from the last failed run's, which is not retried until something changes)."""
        key = self.state.pipeline_key()
        with self.state.lock:
            done = key in (self.state.pipeline_result_key, self.state.pipeline_failed_key)
        if not done:
            self.request()

    def stop(self) -> None:
        with self._wake:
            self._stopped = True
            self._wake.notify()

    def _run(self) -> None:
        while True:
            with self._wake:
                self._wake.wait_for(lambda: self._pending or self._stopped)
                if self._stopped:
                    return
                self._pending = False
            key = self.state.pipeline_key()
            with self.state.lock:
                if key in (self.state.pipeline_result_key, self.state.pipeline_failed_key):
                    continue
            try:
                self._compute(key)
            except Exception as exc:  # keep the app alive; show what went wrong
                traceback.print_exc()
                self.state.set_pipeline_failed(key, f"failed: {exc}")

    def _compute(self, key: tuple) -> None:
        frame_index, params, use_refined, _ = key
        dataset = self.state.dataset
        if use_refined and self.calibrate and dataset.num_sensors > 1 and self._refined_extrinsics is None:
            self.state.set_pipeline_progress("refining the sensor extrinsics (ICP, once)", 0.02)
            detector = Detector(params).calibrate(dataset.frame(frame_index))
            self._refined_extrinsics = detector.T_vehicle_sensor
        extrinsics = self._refined_extrinsics if use_refined else None
        detector = Detector(params, extrinsics, model=self.state.model)
        frame = dataset.frame(frame_index)
        first = max(0, frame_index - params.history_frames)
        history = [dataset.frame(i) for i in range(first, frame_index)]

        def progress(stage: str, fraction: float) -> None:
            self.state.set_pipeline_progress(f"frame {frame_index + 1}: {stage} done", fraction)

        self.state.set_pipeline_progress(f"frame {frame_index + 1}: merging", 0.05)
        if detector.model is not None:
            detection = detector.detect(frame, history, progress=progress)
            result = detection.proposal
        else:
            detection, result = None, detector.propose(frame, history, progress=progress)
        if self.state.pipeline_key() != key:
            # The user moved on: a newer request is queued, unless they came back to the frame
            # and parameters of the result already shown, which is then current again.
            with self.state.lock:
                back_to_shown = self.state.pipeline_result_key == self.state.pipeline_key()
            if back_to_shown:
                self.state.set_pipeline_progress("showing the current result", 1.0, busy=False)
            return
        segmentation = result.segmentation
        status = (
            f"frame {frame_index + 1}: {len(result.proposals):,} proposals, {segmentation.num_segments:,} "
            f"segments, {segmentation.num_patches:,} patches, {result.grid.num_voxels:,} voxels in "
            f"{result.timings_ms['total'] / 1000:.1f} s"
            + (" (refined extrinsics)" if extrinsics is not None else "")
        )
        if detection is None:
            self.state.set_pipeline_result(key, result, status)
            return
        status += f"; classified and NMS in {detection.timings_ms['total'] / 1000:.1f} s in all"
        self.state.set_detection_result(key, detection, status)
