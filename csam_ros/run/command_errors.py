"""The ``csam`` command's last resort for bad input: the errors that readers raise, each said
as one line (exit code 2)."""

from __future__ import annotations


def input_errors() -> tuple[type[BaseException], ...]:
    """The errors that bad input raises (each reader names the file and line or key): input
    a run cannot use, a malformed config, scenario (a ConfigFileError), data set, 2D SLAM
    file, summary.json or bag, a missing or unreadable file, a file that is not text."""
    from csam_ros.bag import BagError
    from csam_ros.core.joining.result import SummaryError
    from csam_ros.core.model.config_file import ConfigFileError
    from csam_ros.datasets.mrclam import MrclamFormatError
    from csam_ros.datasets.slam2d import Slam2dFormatError
    from csam_ros.run.errors import RunError

    readers = (ConfigFileError, MrclamFormatError, Slam2dFormatError, SummaryError, BagError)
    return (RunError, *readers, OSError, UnicodeDecodeError)


def one_line(err: BaseException) -> str:
    """An error as one line; an OSError names its file."""
    if isinstance(err, OSError) and err.filename is not None and err.strerror:
        text = f"{err.filename}: {err.strerror}"
    else:
        text = str(err) or type(err).__name__
    return " ".join(text.split())
