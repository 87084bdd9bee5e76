"""A long member is not lost to an interrupt (issue 40, item 8): a record run in segments saves each finished
segment (its samples in OUT.nc.tmp, what its kernel and noise continue from in the parts folder), and --resume
continues from the last one to the bits of an uninterrupted run. Ctrl-C in a 10-minute single-member run used to
keep nothing."""
from __future__ import annotations

import netCDF4
import numpy as np
import pytest

from ensemble import cli, parts, records, runner
from ensemble.parts import folder_of
from ensemble.spec import load, parse

from .conftest import top_runfile
from .test_resume import _run_with, same_bits

# two methods: a chunk holds two groups of members that run one after the other, each in segments
NOISY_GROWING = (top_runfile(members=4, t_end=1.0, save_dt=0.01, method=None)
                 + '[observe]\nnoise = { tilt = 0.01 }\n[measure]\ngrowth = true\n'
                 + '[[sweep]]\nmethod = ["rk4"]\n[[sweep]]\nmethod = ["dopri5"]\nrtol = [1e-8]\n')


@pytest.fixture
def small_segments(monkeypatch):
    """Records in segments of 2 samples (a kernel block's share of the data outgrows CHUNK_BYTES)."""
    monkeypatch.setattr(runner, "CHUNK_BYTES", 20_000)


def _interrupted_after(spec, out, saves: int, monkeypatch) -> None:
    """runner.run, interrupted (KeyboardInterrupt) just after the `saves`-th segment is saved."""
    real, done = parts.SegmentLog.save, []

    def save(self, *args):
        real(self, *args)
        done.append(1)
        if len(done) == saves:
            raise KeyboardInterrupt

    monkeypatch.setattr(parts.SegmentLog, "save", save)
    with pytest.raises(KeyboardInterrupt):
        runner.run(spec, out, progress=False)
    monkeypatch.setattr(parts.SegmentLog, "save", real)


def _segments_added(monkeypatch) -> list[int]:
    """The first sample of every segment the run computes from now on."""
    real, added = records.Record.add, []

    def add(self, start, samples):
        added.append(start)
        return real(self, start, samples)

    monkeypatch.setattr(records.Record, "add", add)
    return added


@pytest.mark.parametrize("suffix", ["nc", "zarr"])
@pytest.mark.parametrize("saves", [3, 51 + 7], ids=["in the first group", "in the second group"])
def test_an_interrupted_long_record_continues_from_its_last_segment(write_runfile, tmp_path, monkeypatch,
                                                                    small_segments, saves, capsys, suffix):
    """Interrupted in its first group of members (rk4) or its second (dopri5, after the first finished), with
    observation noise and growth amplitudes kept along: the resume computes only the segments still missing, and
    the result has the bits of one uninterrupted run; into a NetCDF file or a Zarr store (whose segments are
    checked against the store by whoever continues the range)."""
    path = write_runfile(NOISY_GROWING)
    spec = load(path)
    assert runner.segment_samples(spec) == 2 and spec.n_save == 101  # 51 segments per group
    whole, out = tmp_path / "whole.nc", tmp_path / f"out.{suffix}"
    runner.run(spec, whole, progress=False)
    _interrupted_after(spec, out, saves, monkeypatch)
    assert len(list(folder_of(out).rglob("segment-*.npz"))) == saves  # kept until their chunk's part is made
    added = _segments_added(monkeypatch)
    runner.run(spec, out, progress=True, resume=True)
    line = capsys.readouterr().err.splitlines()[0]
    first, second = min(saves, 51), max(saves - 51, 0)
    assert f"members 0 to 3 continue from sample {min(2 * first, 101)} of 101" in line, line
    assert (f"members 4 to 7 continue from sample {2 * second} of 101" in line) == bool(second), line
    assert len(added) == 2 * 51 - saves
    same_bits(out, whole)
    assert not folder_of(out).exists()


def test_a_changed_sample_drops_its_segment_and_those_after_it(write_runfile, tmp_path, monkeypatch,
                                                               small_segments, capsys):
    """A bit flipped in a finished segment's samples in OUT.nc.tmp: that segment and every later one are dropped,
    said so, and computed again."""
    path = write_runfile(NOISY_GROWING)
    spec = load(path)
    whole, out = tmp_path / "whole.nc", tmp_path / "out.nc"
    runner.run(spec, whole, progress=False)
    _interrupted_after(spec, out, 6, monkeypatch)
    with netCDF4.Dataset(out.with_name("out.nc.tmp"), "a") as nc:
        tilt = nc["tilt"][1, 5]
        nc["tilt"][1, 5] = np.frombuffer((np.float64(tilt).view(np.uint64) ^ np.uint64(1)).tobytes())[0]
    added = _segments_added(monkeypatch)
    runner.run(spec, out, progress=True, resume=True)
    err = capsys.readouterr().err
    assert "continue from sample 4 of 101" in err and "tilt in the result changed since it was written" in err
    assert "follows a segment that was dropped" in err, err
    assert added[0] == 4
    same_bits(out, whole)


def test_ctrl_c_in_a_single_long_member_keeps_its_segments_and_resumes(write_runfile, tmp_path):
    """Through the command line with a real SIGINT, sent after the third segment of one member's record is saved:
    one line naming the samples kept, exit 130; --resume finishes to the bits of an uninterrupted run."""
    path = write_runfile(top_runfile(members=1, t_end=1.0, save_dt=0.01))
    whole, out = tmp_path / "whole.nc", tmp_path / "out.nc"
    assert cli.main(["run", str(path), "-o", str(whole), "--quiet"]) == 0
    patch = """import ensemble.runner as runner
runner.CHUNK_BYTES = 20_000
real, saved = parts.SegmentLog.save, []
def save(self, *args):
    real(self, *args)
    saved.append(1)
    if len(saved) == 3:
        os.kill(os.getpid(), signal.SIGINT)
parts.SegmentLog.save = save"""
    done = _run_with(patch, path, out)
    assert done.returncode == 130, done.stderr
    tmp, folder = out.with_name("out.nc.tmp"), folder_of(out)
    assert done.stderr.splitlines() == [
        f"ensemble: interrupted; samples 0 to {done.stderr.split('samples 0 to ')[1].split()[0]} of members 0 to 0 "
        f"are kept in {tmp} and {folder}; ensemble run {path} -o {out} --resume finishes the run"], done.stderr
    assert int(done.stderr.split("samples 0 to ")[1].split()[0]) >= 5
    resumed = _run_with("import ensemble.runner as runner\nrunner.CHUNK_BYTES = 20_000", path, out, "--resume")
    assert resumed.returncode == 0, resumed.stderr
    same_bits(out, whole)
    assert not folder.exists() and not tmp.exists()


def test_a_long_run_is_cut_into_segments_of_bounded_work():
    """A record that takes a block more than CHUNK_MEMBER_STEPS runs in segments even when its samples are
    small, so that an interrupt loses at most a few seconds of it."""
    spec = parse(top_runfile(members=1, dt=1e-3, t_end=4e5, save_dt=100.0))
    block = runner.run_block(spec)
    steps_per_segment = runner.segment_samples(spec) * 100.0 / 1e-3 * block
    assert steps_per_segment <= runner.CHUNK_MEMBER_STEPS < 2 * steps_per_segment
    assert runner.segment_samples(parse(top_runfile(members=1))) == parse(top_runfile(members=1)).n_save


def test_few_long_members_run_in_a_smaller_block_with_the_same_bits(write_runfile, tmp_path, monkeypatch):
    """9 members (three methods) of 2000 steps, with a chunk's work lowered to 10^5 member-steps: their 128-member
    block would idle 119 lanes for more than that, so they run in a block of 16, to the bits of the block of
    128. (Three tops of 4 x 10^7 rk4 steps took 1.0 s so, against 7.8 s.)"""
    path = write_runfile(top_runfile(members=3, t_end=2.0, save_dt=0.1, method=None)
                         + '[[sweep]]\nmethod = ["rk4", "split2"]\n[[sweep]]\nmethod = ["dopri5"]\nrtol = [1e-8]\n')
    spec = load(path)
    monkeypatch.setattr(runner, "CHUNK_MEMBER_STEPS", 1e30)
    assert runner.few_members_block(spec) is None
    runner.run(spec, tmp_path / "block128.nc", progress=False)
    monkeypatch.setattr(runner, "CHUNK_MEMBER_STEPS", 1e5)
    assert runner.few_members_block(spec) == 16 and runner.run_block(spec) == 128
    blocks = []
    real = runner.launch.Launch.__init__

    def recording(self, scene, method, *args, **kwargs):
        real(self, scene, method, *args, **kwargs)
        blocks.append(self.state0.shape[2])

    monkeypatch.setattr(runner.launch.Launch, "__init__", recording)
    runner.run(spec, tmp_path / "block16.nc", progress=False)
    assert set(blocks) == {16}
    same_bits(tmp_path / "block16.nc", tmp_path / "block128.nc")
