"""Where a command's messages go: the terminal gets warnings and errors (the commands print their
plan, progress and summary themselves); the log file in the run's folder gets everything from
INFO on, with times, including COLMAP's own log during SfM and triangulation."""

import logging
import sys
from pathlib import Path

from pipeline.runtime import quiet_colmap_logs

FORMAT = "%(asctime)s %(levelname)s %(name)s: %(message)s"


def configure(verbose: bool) -> None:
    """The terminal's handler (warnings, or everything with --verbose); the root passes INFO on
    to the log files. Only the command line calls this (libraries just log)."""
    root = logging.getLogger()
    if not root.handlers:  # a caller (a test, an application) that configured logging keeps its own
        terminal = logging.StreamHandler()
        terminal.setLevel(logging.DEBUG if verbose else logging.WARNING)
        terminal.setFormatter(logging.Formatter("%(levelname)s %(name)s: %(message)s"))
        root.addHandler(terminal)
    root.setLevel(logging.DEBUG if verbose else logging.INFO)
    if not verbose:
        logging.getLogger("matplotlib").setLevel(logging.ERROR)  # its font-cache notice on a first run
        # COLMAP's INFO lines off (its warnings and errors stay): glog writes them to stderr in a process that
        # sends them nowhere else, one "Creating SIFT CPU feature extractor" per image of a build with --sift and
        # per query of the sift prior. glog reads this when pycolmap loads, in the local cluster's worker
        # processes, which inherit the environment; here pycolmap is loaded already (by the parser's imports).
        # ``colmap_to_file`` turns them on again, into its file
        level = quiet_colmap_logs()
        if "pycolmap" in sys.modules and level.isdigit():
            sys.modules["pycolmap"].logging.minloglevel = int(level)


def to_file(path: Path) -> Path:
    """Also write every message from INFO on to ``path`` (appended: a resumed run adds to it)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    handler = logging.FileHandler(path)
    handler.setLevel(logging.INFO)
    handler.setFormatter(logging.Formatter(FORMAT))
    logging.getLogger().addHandler(handler)
    return path


def colmap_to_file(folder: Path) -> None:
    """COLMAP's glog lines (about 120 for a small SfM) into ``folder/colmap.INFO*`` instead of the
    terminal; its errors still reach the terminal."""
    import pycolmap
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    pycolmap.logging.logtostderr = False
    pycolmap.logging.alsologtostderr = False
    pycolmap.logging.stderrthreshold = 2  # ERROR
    pycolmap.logging.minloglevel = 0  # INFO, which ``configure`` keeps off the terminal
    pycolmap.logging.set_log_destination(pycolmap.logging.INFO, str(folder / "colmap.INFO."))
