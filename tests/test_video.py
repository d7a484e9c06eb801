"""Videos for people: H.264 that browsers play, large enough, smooth enough,
from the control camera and the people's camera."""

import av
import numpy as np
from conftest import SmallCloth
from fabric_imitation.learning.demo_io import WriteVideo
from fabric_imitation.scenarios.loader import LoadScenario
from fabric_imitation.tools.runs import Simulate


def _probe(path):
    with av.open(str(path)) as container:
        stream = container.streams.video[0]
        frames = sum(1 for _ in container.decode(stream))
        return (
            stream.codec_context.name,
            stream.codec_context.pix_fmt,
            stream.width,
            stream.height,
            float(stream.average_rate),
            frames,
        )


def test_write_video_is_h264_upscaled_to_the_minimum_size(tmp_path):
    frames = [np.full((161, 120, 3), 10 * i, np.uint8) for i in range(7)]
    WriteVideo(tmp_path / "v.mp4", frames, 15, min_size=480)
    codec, pix, w, h, fps, n = _probe(tmp_path / "v.mp4")
    assert (codec, pix, fps, n) == ("h264", "yuv420p", 15.0, 7)
    assert (w, h) == (480, 644)  # x4, rounded up to even sizes
    assert not list(tmp_path.glob("*.partial*"))


def _simulate_small_box(duration, **outputs):
    return Simulate(
        scenario=LoadScenario(scenario_name="box", scenario_text=SmallCloth("vbd")),
        scenario_name="box",
        duration=duration,
        progress=False,
        **outputs,
    )


def test_simulate_writes_both_videos_at_15_fps(tmp_path):
    out = tmp_path / "run.mp4"
    summary = _simulate_small_box(0.4, video=out)
    assert summary["videos"] == [str(out), str(tmp_path / "run.people.mp4")]
    for path in summary["videos"]:
        codec, pix, w, h, fps, n = _probe(path)
        assert (codec, pix, fps) == ("h264", "yuv420p", 15.0)
        assert min(w, h) >= 480
        assert n >= 6  # 0.4 s at 15 per second


def test_a_video_that_cannot_be_written_keeps_the_summary(tmp_path):
    out = tmp_path / "gone" / "run.mp4"  # its folder does not exist
    record = tmp_path / "gone" / "run.html"
    summary = _simulate_small_box(0.2, video=out, record=record)
    assert summary["success"] is not None and "videos" not in summary
    assert summary["output_errors"][0].startswith(f"--video {out}: ")
    assert summary["output_errors"][1].startswith(f"--record {record}: ")
