"""Settings of `felis train ik` (`felis.learning.ik.run`): `IkTrainConfig` and the Posture Estimator's input
variants. Kept apart from the training code (torch, scipy) so the command line reads its defaults without them."""

from __future__ import annotations

from dataclasses import dataclass

from felis.errors import ParameterError
from felis.learning.ik.infer import PE_IN

PE_VARIANTS: dict[int, tuple[int, ...]] = {1: (0,), 3: (-10, -5, 0), 5: tuple(PE_IN)}


@dataclass
class IkTrainConfig:
    """What `felis train ik` trains; the defaults made the shipped weights."""

    corpus: int = 400  # demonstration trajectories (train 80% / validation 10% / test 10%)
    corpus_seed: int = 1
    seed: int = 0  # network initialisation and batch order
    kind: str = "lstm"  # "lstm" or "mlp"
    hidden: int = 64
    layers: int = 2
    pe_frames: int = 5  # Posture Estimator input frames: 1, 3 or 5
    epochs: int = 30
    batch: int = 128  # the paper's
    lr: float = 2e-3
    lr_decay: float = 0.9  # per epoch
    grad_clip: float = 1.0
    stride: int = 2  # every stride-th frame of the training trajectories is a training window
    threads: int = 0  # torch threads; 0: all cores
    recorded: tuple[str, ...] = ()  # run logs (MCAP) of the arm added to the training split

    def check(self) -> None:
        if self.kind not in ("lstm", "mlp"):
            raise ParameterError(f"--kind must be lstm or mlp, got {self.kind!r}")
        if self.pe_frames not in PE_VARIANTS:
            raise ParameterError(f"--pe-frames must be 1, 3 or 5, got {self.pe_frames}")
        for name in ("corpus", "hidden", "layers", "epochs", "batch", "stride"):
            if int(getattr(self, name)) < (3 if name == "corpus" else 1):
                raise ParameterError(f"--{name.replace('_', '-')} too small: {getattr(self, name)}")
        if not (0 < self.lr < 1 and 0 < self.lr_decay <= 1 and self.grad_clip > 0):
            raise ParameterError("learning rate must be in (0, 1), decay in (0, 1], gradient clip > 0")
