"""``felis train`` and ``felis eval``: one group each, every learned skill adding its command to both.

A skill's CLI module (`felis.cli.ik`, `balance`, `landing`, `phase`) exposes ``register_train(sub)`` and
``register_eval(sub)``; `SKILLS` gives their order in ``--help``.
"""

from __future__ import annotations

from felis.cli import balance, ik, landing, phase
from felis.cli.args import group

SKILLS = (ik, balance, landing, phase)


def register(sub) -> None:
    """Add ``felis train WHAT`` and ``felis eval WHAT``."""
    train = group(sub, "train", "train learned controllers: ik, balance, landing, phase", "train_command", "WHAT")
    evl = group(sub, "eval", "evaluate learned controllers: ik, balance, landing, phase", "eval_command", "WHAT")
    for skill in SKILLS:
        skill.register_train(train)
    for skill in SKILLS:
        skill.register_eval(evl)
