"""A real SLAM run scored alike by ``artrack eval`` and by evo's ``evo_ape`` (run as a command when evo
is installed; it is GPL-3 and never imported): TUM fr3 long_office_household at about 1 Hz through
``SlamSystem`` as users run it (its mapping process, each new keyframe mapped before the next frame as in
a lossless run), its final trajectory written as a TUM file and scored against the data set's own
``groundtruth.txt`` with a Sim(3) alignment by both tools."""

import json

import numpy as np
import pytest

from services.slam.system import SlamSystem
from tests.accuracy.slam_sequences import TUM, tum
from tests.data import data_dir
from tests.integration import test_eval_cli as eval_cli

pytestmark = [pytest.mark.integration, pytest.mark.slow]


def test_a_slam_run_gets_the_same_ate_from_artrack_eval_and_evo(tmp_path):
    ape = eval_cli.evo_command("evo_ape")
    folder = data_dir(TUM)
    sequence = tum(folder)
    system = SlamSystem(sequence.camera, wait_for_mapping=True)
    try:
        for stamp_ns, image, _ in sequence.frames:
            system.process(stamp_ns, image)
        trajectory = system.trajectory()
    finally:
        system.close()
    assert len(trajectory) >= 15, f"only {len(trajectory)} of 20 frames tracked"
    stamps = np.array([stamp for stamp, _ in trajectory])
    estimate = eval_cli.write_tum(tmp_path / "slam.txt", np.array([T for _, T in trajectory]), stamps)
    truth = folder / "groundtruth.txt"
    done = eval_cli.artrack("eval", estimate, truth, "--align", "sim3", "--json")
    assert done.returncode == 0, done.stderr
    ours = json.loads(done.stdout)["ate_m"]
    theirs = eval_cli.evo_figures(ape, "tum", truth, estimate, "-as", "--t_max_diff", "0.02")
    print(f"artrack eval {ours}\nevo_ape {theirs}")
    assert set(theirs) == {"rmse", "mean", "median", "max"}
    assert theirs == pytest.approx({k: ours[k] for k in theirs}, abs=2e-6)
    assert ours["rmse"] <= 0.02
