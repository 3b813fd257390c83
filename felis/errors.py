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


class UsageError(FelisError):
    """A command line that argparse rejects (an unknown option, a missing sub-command); exit code 2."""


# --- the serial bus and its devices (felis.drivers) ----------------------------------------------------


class PortError(CommError):
    """The serial port cannot be opened, lacks permission, or vanished."""

    fatal = True


class NoReplyError(CommError):
    """A servo did not answer (missing, wrong baud, or the reply was lost)."""


class CorruptReplyError(CommError):
    """A reply arrived but failed its CRC or was cut short."""


class ServoStatusError(FelisError):
    """A servo answered with an error in its status byte (e.g. Access Error).

    ``detail`` is the decoded status byte (`felis.drivers.dynamixel.protocol.describe_status_error`)."""

    def __init__(self, dxl_id: int, error: int, what: str, detail: str | None = None):
        self.id, self.error = dxl_id, error
        super().__init__(f"servo {dxl_id}: {what}: {detail if detail is not None else f'error byte 0x{error:02x}'}")


class ImuSilentError(CommError):
    """The IMU's port delivered no byte at all in the time allowed."""


class ImuProtocolError(CommError):
    """The IMU's port delivers bytes, but no BNO08x UART-RVC frame among them."""


# --- simulation (felis.sim) -----------------------------------------------------------------------------


class ModelMismatch(FelisError):
    """The MJCF model does not match the robot description."""


class RenderError(FelisError):
    """Offscreen rendering is unavailable (no OpenGL context)."""


# --- learning (felis.learning) --------------------------------------------------------------------------


class PolicyError(FelisError):
    """A landing policy (gene unit, behaviour or ``.npz`` policy file) is inconsistent, missing, corrupt,
    of an unknown format or for another robot. Nothing is driven with it."""


class CheckpointError(FelisError):
    """A training checkpoint is corrupt, of another format, or was written by a run with other settings or
    other motion samples; nothing is resumed from it."""


class SelectorError(FelisError):
    """A case base, selector file, query or selector parameter is unusable: wrong shape, non-finite
    values, a missing, corrupt or foreign file, feature names other than the caller's."""


class EvaluatorError(FelisError):
    """A worker process died mid-map (out of memory, a crash in native code); its results are lost."""
