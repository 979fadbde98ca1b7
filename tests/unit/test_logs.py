"""Log set-up: artrack's own records at the chosen level, other libraries' only from WARNING up
(everything at DEBUG)."""

import logging

import pytest

from services.runtime.logs import setup_logging


@pytest.fixture
def root_logger():
    root = logging.getLogger()
    handlers, level = root.handlers[:], root.level
    yield root
    root.handlers[:] = handlers
    root.setLevel(level)


def emit_all() -> None:
    logging.getLogger("numexpr.utils").info("NumExpr defaulting to 2 threads.")
    logging.getLogger("somelib").warning("a library's warning")
    logging.getLogger("artrack").info("artrack's own line")
    logging.getLogger("services.slam.system").info("a module's line")
    logging.getLogger("artrack.slam").debug("a debug line")


def test_other_libraries_info_lines_are_left_out_at_info(root_logger, capsys):
    setup_logging(level="INFO")
    emit_all()
    err = capsys.readouterr().err
    assert "NumExpr" not in err
    assert "a library's warning" in err and "artrack's own line" in err and "a module's line" in err
    assert "a debug line" not in err


def test_everything_shows_at_debug(root_logger, capsys):
    setup_logging(level="DEBUG")
    emit_all()
    err = capsys.readouterr().err
    for text in ("NumExpr", "a library's warning", "artrack's own line", "a module's line", "a debug line"):
        assert text in err, text
