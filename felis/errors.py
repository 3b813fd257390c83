"""Exceptions an operator can act on.

Every error felis raises on purpose derives from :class:`FelisError`. The CLI prints such an
error as one line (``error: <message>``) and exits non-zero; ``--debug`` shows the traceback.
Messages name the thing that is wrong (file, key, joint, servo) and, where there is one, the fix.
"""

from __future__ import annotations


class FelisError(Exception):
    """Base class: an expected failure with a message meant for the operator."""


class DescriptionError(FelisError):
    """A robot description (``felis/robots/*.toml``) is malformed or impossible.

    The message starts with ``<file>: <key>:`` so the operator can find the line to fix.
    """

    def __init__(self, source: str, key: str, problem: str):
        self.source, self.key, self.problem = source, key, problem
        super().__init__(f"{source}: {key}: {problem}")


class UnknownRobotError(FelisError):
    """A robot name that has no description."""


class ParameterError(FelisError):
    """A command or scenario parameter is out of its valid range (e.g. a negative drop height)."""


class LifecycleError(FelisError):
    """A `Robot` method was called in the wrong lifecycle state (e.g. ``write`` before ``arm``)."""


class CommError(FelisError):
    """Reading or writing the robot failed (lost reply, corrupt packet, vanished servo or port).

    The control loop tolerates a few of these in a row; past its tolerance the watchdog disarms.
    ``fatal`` errors (the port itself is gone) end a run at once.
    """

    fatal: bool = False


class SafetyTrip(FelisError):
    """The safety layer stopped the run (watchdog: read failures or overruns past their limits)."""


class SimulationError(FelisError):
    """The physics became invalid (NaN or diverging state); the episode cannot continue."""


class LogError(FelisError):
    """A run log cannot be written or read (missing file, not an MCAP file, wrong schema)."""


class CalibrationError(FelisError):
    """A calibration step or file is wrong: a bad range, an offset the servo cannot hold, a corrupt or
    mismatched calibration file, a robot id that cannot be a file name. Nothing was written."""


class ServoParamsError(FelisError):
    """A servo parameter file (`felis sysid` output) is missing, malformed, for another robot, names an
    unknown joint or holds a non-finite or negative value. Nothing was written."""


class SysidError(FelisError):
    """System identification cannot proceed: unknown joints, an unusable recording, a fit that failed."""


class TrajectoryError(FelisError):
    """A trajectory file (CSV ``t,x,y,z``) or stream is unusable: missing columns, non-numeric or
    non-finite values, time not increasing, or not at the expected rate. Nothing was run."""


class WeightsError(FelisError):
    """A weights file (``.npz``) is missing, corrupt, for another model or shape, or holds non-finite
    values. The controller refuses it before moving anything."""


class PhaseError(FelisError):
    """Gait data for phase learning is unusable: a run log that is missing, too short or holds NaN joint
    values, a recording that tipped the cat over, or a corrupt or mismatched gait-data file (``.npz``)."""
