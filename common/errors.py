"""Error types that name what was wrong and where; the CLI prints them without a traceback."""


class BallbotError(Exception):
    """Base of every error a user can cause (bad file, bad setting, bad message). The CLI prints it
    on one line and exits with `exit_status`: 2, bad input or settings (retrying cannot help)."""

    exit_status = 2


class CalibrationError(BallbotError):
    """A calibration file or profile that must not be used."""


class ConfigError(BallbotError):
    """A setting out of range or of the wrong type."""


class DecodeError(BallbotError):
    """A message that cannot be decoded into its model (garbage, wrong schema version, bad image)."""


class SourceError(BallbotError):
    """A capture source that cannot be opened or read."""


class ConnectError(BallbotError):
    """No Zenoh router answers, or an endpoint cannot be listened on: perhaps only for now, so the
    exit status is 1 (`up` restarts a service that meets it, as it does a crash)."""

    exit_status = 1


class MissingDependency(BallbotError):
    """An optional dependency of a service or command is not installed. Installing it is the fix,
    restarting is not: exit status 3, on which `up` disables that service (an optional one such as
    the viewer or the ROS 2 bridge) and keeps the others running."""

    exit_status = 3


def require(modules: tuple[str, ...], extra: str, who: str) -> None:
    """Raise MissingDependency naming the pip extra if any of `modules` cannot be imported."""
    import importlib

    missing = []
    for name in modules:
        try:
            importlib.import_module(name)
        except ImportError:
            missing.append(name)
    if missing:
        raise MissingDependency(f"{who} needs {' and '.join(missing)}, which {'is' if len(missing) == 1 else 'are'} "
                                f"not installed: pip install 'ballbot-vision[{extra}]'")


class FileError(BallbotError):
    """A file the user gave that is missing, unreadable, empty, binary, truncated, corrupt or of an
    impossible size (see common/files.py for the one wording every command uses)."""


def path_error(e: OSError) -> str:
    """What went wrong with an OSError's path, in the words common/files.py uses for the same."""
    import errno

    known = {errno.ENOENT: "no such file or folder", errno.EEXIST: "is a file, not a folder",
             errno.ENOTDIR: "a part of the path is a file, not a folder", errno.EISDIR: "is a folder, not a file",
             errno.EACCES: "permission denied", errno.EPERM: "permission denied",
             errno.EROFS: "read-only file system", errno.ENOSPC: "no space left on the device"}
    why = known.get(e.errno or 0) or (e.strerror or str(e)).rstrip(".")
    return why[:1].lower() + why[1:]
