"""Log set-up: artrack's own records at the chosen level, other libraries' only from WARNING up
(everything at DEBUG)."""

import json
import logging

import pytest

from services.runtime.logs import NATIVE_LOGGER, is_native_line, native_record, setup_logging


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


RUST_LINE = ("\x1b[2m2026-11-29T06:55:16.142735Z\x1b[0m \x1b[31mERROR\x1b[0m acc-0 ThreadId(06) "
             "\x1b[2mzenoh_transport::unicast::universal::transport\x1b[0m: link closed")


def test_a_rust_tracing_line_keeps_its_level_and_loses_its_time_and_colours():
    assert native_record(RUST_LINE) == (
        logging.ERROR, "acc-0 ThreadId(06) zenoh_transport::unicast::universal::transport: link closed")
    assert native_record("2026-11-29T06:55:16Z  WARN  a warning\n") == (logging.WARNING, "a warning")
    assert native_record("something else\n") == (logging.WARNING, "something else")


def test_native_lines_are_told_from_a_process_own_lines_in_either_format():
    assert is_native_line(RUST_LINE)
    assert is_native_line(json.dumps({"level": "error", "logger": NATIVE_LOGGER, "message": "x"}))
    assert not is_native_line(json.dumps({"level": "error", "logger": "services.cli", "message": "x"}))
    assert not is_native_line("job: nodes.capture: images:/nope: no such folder")
    assert not is_native_line("{not json")



GLOG_REPORT = """*** Aborted at 1795949955 (unix time) try "date -d @1795949955" if you are using GNU date ***
PC: @     0x7f1ee74fcb74 _PyEval_EvalFrameDefault
*** SIGTERM (@0xba5) received by PID 3019 (TID 0x7f1ee7a04b80) from PID 2981; stack trace: ***
    @     0x7f1ee72ac057 (/usr/lib/x86_64-linux-gnu/libc.so.6+0x8e056)
    @     0x7f1ee75a7332 cfunction_vectorcall_FASTCALL_KEYWORDS
"""
"""What glog's signal handler, which importing pycolmap installs, printed when a process got SIGTERM."""


def test_the_lines_of_glogs_signal_report_are_native():
    assert all(is_native_line(line) for line in GLOG_REPORT.splitlines())
    assert not is_native_line("*** a line of the node's own ***")
    assert not is_native_line("    @ the node's own line")
