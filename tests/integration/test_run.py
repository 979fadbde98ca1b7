"""``artrack run``: a whole job in processes, recorded, ending with its finite source."""

from mcap.reader import make_reader

from protocol import decode
from tests.integration.support import START_S


def test_run_records_a_finite_job_and_exits_cleanly(procs, tmp_path):
    out = tmp_path / "job.mcap"
    job = procs.artrack("run", "echo", "--source", "synthetic:markers", "--frames", "20", "--fps", "30",
                        "--record", str(out), name="job")
    assert job.wait(3 * START_S) == 0, job.describe()
    with open(out, "rb") as f:
        reader = make_reader(f)
        counts: dict[str, int] = {}
        images, echoes = [], []
        for _, channel, message in reader.iter_messages():
            stream = channel.topic.rsplit("/", 1)[-1]
            counts[stream] = counts.get(stream, 0) + 1
            if channel.topic.endswith("/cam0/image"):
                images.append(decode(message.data))
            elif channel.topic.endswith("/cam0/echo"):
                echoes.append(decode(message.data))
    assert counts["image"] == counts["camera_info"] == counts["truth"] == 20, counts
    assert [m.header.seq for m in images] == list(range(20))
    assert {m.header.seq for m in echoes} <= set(range(20)) and len(echoes) >= 15, len(echoes)
    assert all(e == images[e.header.seq] for e in echoes)  # relayed untouched


def test_run_refuses_an_unknown_pipeline_before_starting(procs):
    job = procs.artrack("run", "teleport", "--source", "synthetic:pattern", name="job")
    assert job.wait(START_S) == 2
    assert "unknown pipeline 'teleport'" in job.stderr and "echo" in job.stderr

