"""The benchmarks' pure helpers: measuring order and paired medians; the machine line."""

from __future__ import annotations

import operator
import os

import pytest

from tests.bench.figures import alternating, host, paired_median


def test_alternating_reverses_the_order_every_other_round() -> None:
    assert alternating(["peer", "router"], 3) == [(0, "peer"), (0, "router"), (1, "router"), (1, "peer"),
                                                  (2, "peer"), (2, "router")]


def test_alternating_measures_every_variant_once_a_round() -> None:
    order = alternating(["a", "b", "c"], 4)
    assert [sorted(v for r, v in order if r == round_) for round_ in range(4)] == [["a", "b", "c"]] * 4


def test_paired_median_takes_the_median_of_the_pairs_not_the_ratio_of_medians() -> None:
    first, second = [2.0, 30.0, 4.0], [1.0, 10.0, 4.0]
    assert paired_median(first, second) == 2.0
    assert paired_median(first, second, operator.sub) == 1.0


def test_paired_median_of_an_even_count_is_the_mean_of_the_middle_two() -> None:
    assert paired_median([1.1, 1.5], [1.0, 1.0]) == pytest.approx(1.3)


@pytest.mark.parametrize(("first", "second"), [([], []), ([1.0], [1.0, 2.0])])
def test_paired_median_refuses_unpaired_figures(first: list[float], second: list[float]) -> None:
    with pytest.raises(ValueError, match="equally long"):
        paired_median(first, second)


def test_host_line_names_the_machine_and_how_fast_it_runs_now() -> None:
    line = host(bench="layouts")
    with open("/proc/cpuinfo") as cpuinfo:
        models = {row.split(":", 1)[1].strip() for row in cpuinfo if row.startswith("model name")}
    assert line["bench"] == "layouts" and line["variant"] == "machine"
    assert line["cpu"] in models and line["cpus"] == os.cpu_count()
    assert len(line["load_average"]) == 3
    assert 1.0 < line["room_fps"] < 100_000.0
