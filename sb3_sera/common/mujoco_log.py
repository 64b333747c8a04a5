"""MuJoCo's warnings, once the package is imported: through Python's warnings, never into ``MUJOCO_LOG.TXT``."""

import warnings

#: MuJoCo 4 warns, for every HalfCheetah env it builds, that Gymnasium's model uses the deprecated ``settotalmass``:
#: a fact of Gymnasium's model file, not of the user's run
KNOWN_MODEL_WARNINGS = ("compiler attribute 'settotalmass' is deprecated",)


def route_mujoco_warnings() -> None:
    """
    Send MuJoCo's warnings to Python's ``warnings`` (as ``RuntimeWarning``, so that a filter can silence or raise
    them) instead of the console and ``MUJOCO_LOG.TXT`` in the working directory, and drop
    :data:`KNOWN_MODEL_WARNINGS`. ``import sb3_sera`` calls it, and so do the ``sb3-sera`` command's run workers.
    Does nothing without MuJoCo.
    """
    try:
        import mujoco
    except ImportError:
        return
    if hasattr(mujoco, "MjLogConfig"):
        # MuJoCo 4 logs to the file by its configuration; MuJoCo 3 only where no handler is set (below)
        config = mujoco.MjLogConfig.get()
        config.logto_file = False
        config.set()

    def handler(message: str) -> None:
        if not any(known in message for known in KNOWN_MODEL_WARNINGS):
            warnings.warn(f"MuJoCo: {message}", RuntimeWarning, stacklevel=2)

    mujoco.set_mju_user_warning(handler)
