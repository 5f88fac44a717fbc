"""The 3DmFV-Net classifier of proposals (paper §3.5; Ben-Shabat et al. 2018), with a width knob.

``FisherNet`` is the network: inception blocks on the [20, 5, 5, 5] Fisher-vector grid, max
pooling, and fully connected layers with dropout. At ``width=1`` it is the published network
(about 46M parameters); the default ``width=0.0625`` (about 190k parameters with the descriptor
branch) trains on a 2-core CPU in minutes.

``ProposalClassifier`` wraps it the scikit-learn way: settings in ``__init__``, ``fit`` returns
``self``, ``predict_proba`` gives one column per class of ``labels_`` (the object classes, then
"background" last). Checkpoints are a state dict (``.pt``) with a JSON note beside it.

With ``geometry=True`` the network also reads each point set's geometric descriptors
(``groups.DESCRIPTOR_NAMES``: box size, height above the floor, eigenvalue features, density),
standardised and joined to the flattened convolution output before the fully connected layers.
The 3DmFV tensor describes shape but not absolute size (the aggregated feature is a mean of
per-voxel vectors, the direct one is scaled into the unit sphere), and the classes here differ
first by size: a cone and a truck can look alike once normalised. ``bench classifier`` measures
both inputs side by side.
"""

from __future__ import annotations

import contextlib
import dataclasses
import hashlib
import os
import time
from collections.abc import Callable, Mapping
from pathlib import Path
from typing import ClassVar

import numpy as np
import torch
from torch import nn

from factorydet_core.detection.checkpoint import (
    BACKGROUND,
    MAX_SEED,
    check_class_names,
    check_note_record,
    load_weights,
    read_checkpoint_note,
    write_checkpoint,
)
from factorydet_core.detection.groups import DESCRIPTOR_NAMES
from factorydet_core.settings_check import Setting, check_settings
from factorydet_core.types import CLASS_NAMES, Cancelled, InputError

CLASS_WEIGHTS = (None, "balanced", "sqrt")
FEATURE_SHAPE = (20, 5, 5, 5)

MAX_WIDTH = 2.0
"""The widest ``FisherNet`` a classifier may have: twice the published network (``width=1``, 46M
parameters), 183M parameters (0.7 GB). A hand-edited note's ``"width": 64`` asked for 5.8 GB."""

SETTINGS: dict[str, Setting] = {
    "width": Setting(float, 0.0, MAX_WIDTH, low_open=True),
    "epochs": Setting(int, 1, 1_000_000),
    "batch_size": Setting(int, 2, 2**20),
    "learning_rate": Setting(float, 0.0, 10.0, low_open=True),
    "lr_decay": Setting(float, 0.0, 1.0, low_open=True),
    "decay_every_samples": Setting(int, 1),
    "dropout": Setting(float, 0.0, 1.0),
    "class_weight": Setting(str, optional=True, choices=tuple(w for w in CLASS_WEIGHTS if w)),
    "seed": Setting(int, 0, MAX_SEED),
    "num_threads": Setting(int, 1, 1024, optional=True),
    "max_fit_seconds": Setting(float, 0.0, optional=True, low_open=True),
    "geometry": Setting(bool),
}
"""What each setting of ``ProposalClassifier`` may be (checked when it is made, and so in a
checkpoint's note before its network is built); ``class_names`` by ``check_class_names``."""


def _conv(in_channels: int, out_channels: int, kernel: int) -> nn.Sequential:
    """Convolution with SAME padding, then batch norm and ReLU (every convolution of the net)."""
    return nn.Sequential(
        nn.Conv3d(in_channels, out_channels, kernel, padding=kernel // 2, bias=False),
        nn.BatchNorm3d(out_channels),
        nn.ReLU(inplace=True),
    )


class Inception(nn.Module):
    """Four branches concatenated into ``3 * num_filters`` channels: 1x1x1; 1x1x1 then 3x3x3;
    1x1x1 then 5x5x5; 3x3x3 average pool then 1x1x1."""

    def __init__(self, in_channels: int, num_filters: int) -> None:
        super().__init__()
        half = max(1, num_filters // 2)
        self.reduce = _conv(in_channels, num_filters, 1)
        self.conv3 = _conv(num_filters, half, 3)
        self.conv5 = _conv(num_filters, half, 5)
        self.pool = nn.Sequential(
            nn.AvgPool3d(3, stride=1, padding=1, count_include_pad=False), _conv(in_channels, num_filters, 1)
        )
        self.out_channels = num_filters + 2 * half + num_filters

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        reduced = self.reduce(x)
        return torch.cat([reduced, self.conv3(reduced), self.conv5(reduced), self.pool(x)], dim=1)


class FisherNet(nn.Module):
    """3DmFV-Net on a (B, 20, n, n, n) input; ``width`` scales every layer's channels.

    ``num_descriptors`` > 0 adds a (B, num_descriptors) input, standardised by the buffers
    ``descriptor_mean`` and ``descriptor_scale`` (set from the training data, saved in the state
    dict), passed through its own two fully connected layers and concatenated to the flattened
    convolution output. The branch keeps the few descriptors from being drowned by the hundreds of
    convolution outputs (joined directly, the network fitted noise in the tensor instead).
    """

    DESCRIPTOR_UNITS = 64

    def __init__(
        self,
        num_classes: int = 8,
        width: float = 1.0,
        dropout: float = 0.3,
        in_channels: int = 20,
        num_descriptors: int = 0,
    ) -> None:
        super().__init__()
        self.num_descriptors = num_descriptors
        if num_descriptors:  # no buffers without descriptors: the paper's state dict stays as it was
            self.register_buffer("descriptor_mean", torch.zeros(num_descriptors))
            self.register_buffer("descriptor_scale", torch.ones(num_descriptors))

        def scaled(n: int) -> int:
            return max(2, int(round(n * width)))

        blocks = []
        channels = in_channels
        for n in (64, 128, 256):
            blocks.append(Inception(channels, scaled(n)))
            channels = blocks[-1].out_channels
        blocks.append(nn.MaxPool3d(2, 2, ceil_mode=True))  # TF "SAME" pooling on odd sizes: 5 -> 3
        for n in (256, 512):
            blocks.append(Inception(channels, scaled(n)))
            channels = blocks[-1].out_channels
        blocks.append(nn.MaxPool3d(2, 2, ceil_mode=True))  # 3 -> 2
        self.features = nn.Sequential(*blocks)
        self.descriptor_branch = None
        width_in = channels * 8
        if num_descriptors:
            units = self.DESCRIPTOR_UNITS
            self.descriptor_branch = nn.Sequential(
                nn.Linear(num_descriptors, units, bias=False),
                nn.BatchNorm1d(units),
                nn.ReLU(inplace=True),
                nn.Linear(units, units, bias=False),
                nn.BatchNorm1d(units),
                nn.ReLU(inplace=True),
            )
            width_in += units
        # The head starts with a (no-op) Flatten so that its layers keep the state-dict indices
        # of checkpoints written before the descriptor branch existed.
        layers: list[nn.Module] = [nn.Flatten()]
        for n in (1024, 256, 128):
            layers += [
                nn.Linear(width_in, scaled(n), bias=False),
                nn.BatchNorm1d(scaled(n)),
                nn.ReLU(inplace=True),
                nn.Dropout(dropout),
            ]
            width_in = scaled(n)
        layers.append(nn.Linear(width_in, num_classes))
        self.head = nn.Sequential(*layers)

    def forward(self, x: torch.Tensor, descriptors: torch.Tensor | None = None) -> torch.Tensor:
        flat = torch.flatten(self.features(x), 1)
        if self.num_descriptors:
            if descriptors is None:
                raise ValueError("this network needs descriptors")
            standardised = (descriptors - self.descriptor_mean) / self.descriptor_scale
            flat = torch.cat([flat, self.descriptor_branch(standardised)], dim=1)
        return self.head(flat)


def class_weights(counts: np.ndarray, kind: str | None) -> torch.Tensor | None:
    """Cross-entropy weights of classes with (C,) training ``counts``: ``None`` (plain loss),
    ``"balanced"`` (inverse frequency: every class weighs as much in total) or ``"sqrt"`` (inverse
    square root of the frequency: rare classes still count more, but a rare class's error no longer
    costs hundreds of times a background error, which made the net call structure "pallet").
    Absent classes get 0; the weights average 1 over the samples."""
    if kind is None:
        return None
    counts = np.asarray(counts, np.float64)
    present = counts > 0
    w = np.zeros_like(counts)
    w[present] = 1.0 / counts[present] if kind == "balanced" else 1.0 / np.sqrt(counts[present])
    w *= counts.sum() / max((w * counts).sum(), 1e-12)
    return torch.as_tensor(w, dtype=torch.float32)


FINE_TUNE_RATE = 0.25
"""A fit that goes on from a fitted model (``init_model``) runs at this share of the learning
rate: hard-negative mining rounds fine-tune the previous round's network instead of training
afresh, and at the full rate the first steps would undo much of what it had learnt."""


def check_init_model(model, init_model) -> None:
    """Raise ``InputError`` unless ``init_model`` is a fitted model of ``model``'s type whose
    class names and network settings (its class's ``ARCHITECTURE``) are ``model``'s: a fit can go
    on from its weights."""
    if type(init_model) is not type(model) or not hasattr(init_model, "network_"):
        kind = type(model).__name__
        raise InputError(f"init_model must be a fitted {kind}, got {type(init_model).__name__}")
    differing = [
        name
        for name in ("class_names", *model.ARCHITECTURE)
        if getattr(init_model, name) != getattr(model, name)
    ]
    if differing:
        raise InputError(f"init_model differs in {', '.join(differing)}: its weights cannot be continued")


def count_parameters(module: nn.Module) -> int:
    return int(sum(p.numel() for p in module.parameters()))


def data_hash(features: np.ndarray, labels: np.ndarray, descriptors: np.ndarray | None = None) -> str:
    """Short content hash of a training set, stored with checkpoints."""
    digest = hashlib.sha256()
    digest.update(np.ascontiguousarray(features, np.float32).tobytes())
    digest.update(np.ascontiguousarray(labels, np.int64).tobytes())
    if descriptors is not None:
        digest.update(np.ascontiguousarray(descriptors, np.float32).tobytes())
    return digest.hexdigest()[:16]


@contextlib.contextmanager
def _torch_threads(num_threads: int | None):
    if num_threads is None:
        yield
        return
    previous = torch.get_num_threads()
    torch.set_num_threads(num_threads)
    try:
        yield
    finally:
        torch.set_num_threads(previous)


class ClassOutputs:
    """What the project's learned classifiers share: object classes in ``class_names``, one output
    column per class of ``labels_`` (background last), and scikit-learn's ``get_params``."""

    class_names: tuple[str, ...]

    @property
    def labels_(self) -> tuple[str, ...]:
        """Names of the output columns: the object classes, then background."""
        return (*self.class_names, BACKGROUND)

    @property
    def background_id(self) -> int:
        return len(self.class_names)

    def get_params(self) -> dict:
        return {f.name: getattr(self, f.name) for f in dataclasses.fields(self)}

    def with_weights(self, path: str | os.PathLike, meta: dict):
        """This unfitted model (``from_note(meta, ...)``) fitted with the weights at ``path``
        (checked against its network, ``checkpoint.load_weights``) and its note's records;
        ``note_`` holds the note. Returns ``self``."""
        self.network_ = load_weights(self._new_network(), path)
        self.history_ = meta.get("history", [])
        self.fit_seconds_ = float(meta.get("fit_seconds", 0.0))
        self.num_parameters_ = count_parameters(self.network_)
        self.train_counts_ = meta.get("train_counts", {})
        self.note_ = meta
        return self


@dataclasses.dataclass
class ProposalClassifier(ClassOutputs):
    """3DmFV-Net proposal classifier.

    Args:
        width: channel multiplier of ``FisherNet`` (1.0 is the published network), at most
            ``MAX_WIDTH``.
        epochs: passes over the training set.
        batch_size: the paper's 64.
        learning_rate: Adam's initial rate (the paper's 0.001).
        lr_decay: the rate is multiplied by this every ``decay_every_samples`` samples (0.7).
        decay_every_samples: samples between decays.
        dropout: dropout probability of the fully connected layers (the paper keeps 0.7).
        class_weight: ``"balanced"`` (each class weighted by the inverse of its frequency; the
            default, because positives are a few percent of a mined training set here) or ``None``
            (plain cross-entropy, the paper's).
        class_names: the object classes; ``labels_`` appends "background".
        seed: seeds weights and batch order.
        num_threads: torch threads while fitting and predicting (``None``: torch's default).
        max_fit_seconds: stop after the batch during which this much time has passed (for
            equal-time comparisons of widths); ``None`` runs every epoch.
        geometry: also read each point set's geometric descriptors (``fit`` and
            ``predict_proba`` then need them); ``False`` is the paper's network on the 3DmFV
            tensor alone.
    """

    width: float = 0.0625
    epochs: int = 20
    batch_size: int = 64
    learning_rate: float = 1e-3
    lr_decay: float = 0.7
    decay_every_samples: int = 200_000
    dropout: float = 0.3
    class_weight: str | None = "balanced"
    class_names: tuple[str, ...] = CLASS_NAMES
    seed: int = 0
    num_threads: int | None = None
    max_fit_seconds: float | None = None
    geometry: bool = True

    ARCHITECTURE: ClassVar[tuple[str, ...]] = ("width", "geometry")
    """The settings that shape the network's weights: a fit goes on only from a classifier that
    shares them (``check_init_model``)."""

    @property
    def input_kind(self) -> str:
        """What ``predict_proba`` reads from ``groups.ProposalGroups``."""
        return "features+descriptors" if self.geometry else "features"

    def __post_init__(self) -> None:
        checked = check_settings(self.get_params(), SETTINGS)
        checked["class_names"] = check_class_names(self.class_names)
        for name, value in checked.items():
            setattr(self, name, value)

    def _new_network(self) -> FisherNet:
        num_descriptors = len(DESCRIPTOR_NAMES) if self.geometry else 0
        return FisherNet(len(self.labels_), self.width, self.dropout, num_descriptors=num_descriptors)

    def _check_inputs(
        self, features: np.ndarray, descriptors: np.ndarray | None
    ) -> tuple[np.ndarray, np.ndarray | None]:
        features = np.asarray(features, np.float32)
        if features.ndim != 5 or features.shape[1:] != FEATURE_SHAPE:
            raise InputError(f"features: expected shape (M, 20, 5, 5, 5), got {features.shape}")
        if not np.isfinite(features).all():
            raise InputError("features hold NaN or Inf values")
        if not self.geometry:
            return features, None
        if descriptors is None:
            raise InputError("this classifier reads geometric descriptors (geometry=True); pass them")
        descriptors = np.asarray(descriptors, np.float32)
        if descriptors.shape != (len(features), len(DESCRIPTOR_NAMES)):
            raise InputError(
                f"descriptors: expected shape ({len(features)}, {len(DESCRIPTOR_NAMES)}),"
                f" got {descriptors.shape}"
            )
        if not np.isfinite(descriptors).all():
            raise InputError("descriptors hold NaN or Inf values")
        return features, descriptors

    def fit(
        self,
        features: np.ndarray,
        labels: np.ndarray,
        descriptors: np.ndarray | None = None,
        progress: Callable[[int, int], None] | None = None,
        should_stop: Callable[[], bool] | None = None,
        init_model: ProposalClassifier | None = None,
    ) -> ProposalClassifier:
        """Train from scratch, or go on training ``init_model``.

        Args:
            features: (M, 20, 5, 5, 5) proposal features.
            labels: (M,) ints into ``labels_`` (``background_id`` for background).
            descriptors: (M, len(DESCRIPTOR_NAMES)) geometric descriptors; needed with
                ``geometry=True``, ignored otherwise.
            progress: called with (epoch, epochs) after each epoch.
            should_stop: asked before every batch; when it returns True, fit raises ``Cancelled``
                and the classifier is left as it was.
            init_model: a fitted classifier of the same classes and network whose weights (and
                descriptor normalisation) the fit starts from, for ``epochs`` more epochs at
                ``FINE_TUNE_RATE`` times the learning rate; it is not changed. ``None``: fresh weights.

        Returns:
            self, with ``network_``, ``history_`` (loss and accuracy per epoch) and ``fit_seconds_``.
        """
        features, descriptors = self._check_inputs(features, descriptors)
        if init_model is not None:
            check_init_model(self, init_model)
        labels = np.asarray(labels, np.int64)
        if labels.shape != (len(features),):
            raise InputError(f"labels: expected shape ({len(features)},), got {labels.shape}")
        if len(features) < 2:
            raise InputError("fit needs at least 2 samples")
        if labels.min() < 0 or labels.max() >= len(self.labels_):
            raise InputError(f"labels must lie in [0, {len(self.labels_)})")
        start = time.perf_counter()
        with _torch_threads(self.num_threads):
            torch.manual_seed(self.seed)
            network = self._new_network()
            d_all = None if descriptors is None else torch.from_numpy(descriptors)
            learning_rate = self.learning_rate
            if init_model is not None:
                network.load_state_dict(init_model.network_.state_dict())
                learning_rate *= FINE_TUNE_RATE
            elif d_all is not None:
                network.descriptor_mean.copy_(d_all.mean(dim=0))
                network.descriptor_scale.copy_(d_all.std(dim=0).clamp_min(1e-3))
            counts = np.bincount(labels, minlength=len(self.labels_)).astype(np.float64)
            weight = class_weights(counts, self.class_weight)
            loss_fn = nn.CrossEntropyLoss(weight=weight)
            optimizer = torch.optim.Adam(network.parameters(), lr=learning_rate)
            x_all = torch.from_numpy(features)
            y_all = torch.from_numpy(labels)
            generator = torch.Generator().manual_seed(self.seed)
            history = []
            samples_seen = 0
            for epoch in range(self.epochs):
                network.train()
                order = torch.randperm(len(x_all), generator=generator)
                total_loss, correct = 0.0, 0
                out_of_time = False
                for lo in range(0, len(order), self.batch_size):
                    if should_stop is not None and should_stop():
                        raise Cancelled("training cancelled")
                    if (
                        self.max_fit_seconds is not None
                        and time.perf_counter() - start > self.max_fit_seconds
                    ):
                        out_of_time = True
                        break
                    batch = order[lo : lo + self.batch_size]
                    if len(batch) < 2:  # batch norm needs two samples
                        continue
                    decays = samples_seen // self.decay_every_samples
                    for group in optimizer.param_groups:
                        group["lr"] = max(learning_rate * self.lr_decay**decays, 1e-5)
                    logits = network(x_all[batch], None if d_all is None else d_all[batch])
                    loss = loss_fn(logits, y_all[batch])
                    optimizer.zero_grad()
                    loss.backward()
                    optimizer.step()
                    samples_seen += len(batch)
                    total_loss += float(loss.detach()) * len(batch)
                    correct += int((logits.argmax(1) == y_all[batch]).sum())
                seen = max(min(lo, len(order)) if out_of_time else len(order), 1)
                history.append(
                    {
                        "epoch": epoch + 1 if not out_of_time else round(epoch + seen / len(order), 2),
                        "loss": round(total_loss / seen, 4),
                        "train_accuracy": round(correct / seen, 4),
                    }
                )
                if progress is not None:
                    progress(epoch + 1, self.epochs)
                if out_of_time:
                    break
        network.eval()
        self.network_ = network
        self.history_ = history
        self.fit_seconds_ = time.perf_counter() - start
        self.num_parameters_ = count_parameters(network)
        self.train_hash_ = data_hash(features, labels, descriptors)
        self.train_counts_ = {name: int(c) for name, c in zip(self.labels_, counts)}
        return self

    def predict_proba(
        self, features: np.ndarray, descriptors: np.ndarray | None = None, batch_size: int = 512
    ) -> np.ndarray:
        """(M, len(labels_)) class probabilities of (M, 20, 5, 5, 5) features (and, with
        ``geometry=True``, their (M, len(DESCRIPTOR_NAMES)) descriptors)."""
        if not hasattr(self, "network_"):
            raise InputError("the classifier is not fitted; call fit or load a checkpoint")
        features, descriptors = self._check_inputs(features, descriptors)
        out = np.zeros((len(features), len(self.labels_)), np.float32)
        with _torch_threads(self.num_threads), torch.inference_mode():
            self.network_.eval()
            for lo in range(0, len(features), batch_size):
                batch_descriptors = None
                if descriptors is not None:
                    batch_descriptors = torch.from_numpy(descriptors[lo : lo + batch_size])
                logits = self.network_(torch.from_numpy(features[lo : lo + batch_size]), batch_descriptors)
                out[lo : lo + batch_size] = torch.softmax(logits, dim=1).numpy()
        return out

    def predict(self, features: np.ndarray, descriptors: np.ndarray | None = None) -> np.ndarray:
        """(M,) most probable label ids."""
        return self.predict_proba(features, descriptors).argmax(axis=1)

    def save(
        self,
        path: str | os.PathLike,
        note: dict | None = None,
        companions: Mapping[str, str | os.PathLike] | None = None,
    ) -> Path:
        """Write the state dict to ``path`` (.pt) and a JSON note beside it (``path`` with .json):
        the settings, labels, training data hash, parameter count, history and ``note``. The note
        records the files' sizes and hashes, with those of ``companions`` (``write_checkpoint``)."""
        if not hasattr(self, "network_"):
            raise InputError("the classifier is not fitted; nothing to save")
        meta = {
            "format": "factorydet-classifier/1",
            "params": {**self.get_params(), "class_names": list(self.class_names)},
            "labels": list(self.labels_),
            "num_parameters": self.num_parameters_,
            "train_hash": self.train_hash_,
            "train_counts": self.train_counts_,
            "fit_seconds": round(self.fit_seconds_, 2),
            "history": self.history_,
            **(note or {}),
        }
        return write_checkpoint(self.network_, path, meta, companions)

    @classmethod
    def from_note(cls, meta: dict, note_path: Path) -> ProposalClassifier:
        """The unfitted classifier a checkpoint's note describes, every setting and record of the
        note checked (``SETTINGS``, ``checkpoint.check_note_record``); no network is built."""
        params = meta.get("params")
        if not isinstance(params, dict) or "class_names" not in params:
            raise InputError(f"{note_path}: malformed checkpoint note (no params with class_names)")
        params = {"geometry": False, **params}  # checkpoints from before the option existed
        if isinstance(params["class_names"], list):
            params["class_names"] = tuple(params["class_names"])
        known = {f.name for f in dataclasses.fields(cls)}
        try:
            model = cls(**{k: v for k, v in params.items() if k in known})
        except InputError as exc:
            raise InputError(f"{note_path}: {exc}") from None
        check_note_record(meta, model.class_names, str(note_path))
        return model

    @classmethod
    def load(cls, path: str | os.PathLike) -> ProposalClassifier:
        """A fitted classifier from a checkpoint written by ``save``; ``note_`` holds the JSON note.
        The note is checked before the network is built (``from_note``), and the weights' shapes
        against the network's (``checkpoint.read_state_dict``)."""
        meta = read_checkpoint_note(path)
        return cls.from_note(meta, Path(path).with_suffix(".json")).with_weights(path, meta)

    def with_weights(self, path: str | os.PathLike, meta: dict) -> ProposalClassifier:
        """``ClassOutputs.with_weights``, and the hash of the data it was trained on."""
        super().with_weights(path, meta)
        self.train_hash_ = meta.get("train_hash", "")
        return self
