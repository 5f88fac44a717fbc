"""A non-deep baseline on the same proposals: gradient-boosted trees on hand-made geometric
descriptors of each point set (``groups.DESCRIPTOR_NAMES``), standing where the paper put its
SVM 3D-DPM baseline."""

from __future__ import annotations

import dataclasses
import time

import numpy as np

from factorydet_core.detection.classifier import BACKGROUND
from factorydet_core.detection.groups import DESCRIPTOR_NAMES
from factorydet_core.types import CLASS_NAMES, InputError


@dataclasses.dataclass
class BaselineClassifier:
    """scikit-learn's histogram gradient boosting on geometric descriptors.

    Args:
        max_iter: boosting iterations.
        learning_rate: shrinkage.
        class_names: the object classes; ``labels_`` appends "background".
        seed: random state.
    """

    max_iter: int = 200
    learning_rate: float = 0.1
    class_names: tuple[str, ...] = CLASS_NAMES
    seed: int = 0

    input_kind = "descriptors"

    @property
    def labels_(self) -> tuple[str, ...]:
        return (*self.class_names, BACKGROUND)

    def fit(self, descriptors: np.ndarray, labels: np.ndarray) -> BaselineClassifier:
        """Train on (M, D) descriptors and (M,) label ids into ``labels_``."""
        from sklearn.ensemble import HistGradientBoostingClassifier

        descriptors = np.asarray(descriptors, np.float32)
        if descriptors.ndim != 2 or descriptors.shape[1] != len(DESCRIPTOR_NAMES):
            raise InputError(
                f"descriptors: expected shape (M, {len(DESCRIPTOR_NAMES)}), got {descriptors.shape}"
            )
        start = time.perf_counter()
        self.model_ = HistGradientBoostingClassifier(
            max_iter=self.max_iter, learning_rate=self.learning_rate, random_state=self.seed
        ).fit(descriptors, np.asarray(labels, np.int64))
        self.fit_seconds_ = time.perf_counter() - start
        return self

    def predict_proba(self, descriptors: np.ndarray) -> np.ndarray:
        """(M, len(labels_)) probabilities; classes absent from training get 0."""
        if not hasattr(self, "model_"):
            raise InputError("the baseline is not fitted")
        out = np.zeros((len(descriptors), len(self.labels_)), np.float32)
        if len(descriptors):
            out[:, self.model_.classes_] = self.model_.predict_proba(np.asarray(descriptors, np.float32))
        return out
