"""`ros2 run ad_sim generate`: CLI, sharding, resume after kill -9, determinism, instance files."""

from __future__ import annotations

import json
import shutil
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
import yaml
from rosbags.highlevel import AnyReader
from rosbags.typesys import Stores, get_types_from_msg, get_typestore
from ros_procs import ADRUN, REPO_ROOT
from sim_fixtures import as_plain

from ad_sim import messages
from ad_sim.generate import DONE_MARKER, main, parse_shard
from ad_sim.rosbag import BagReader, group_episodes


def generate(*args: str, **kwargs) -> subprocess.Popen:
    """`python -m ad_sim.generate` (what `ros2 run ad_sim generate` runs) as a subprocess."""
    return subprocess.Popen(
        [sys.executable, "-m", "ad_sim.generate", "--quiet", *args],
        cwd=REPO_ROOT, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, **kwargs,
    )


def digests(folder):
    return json.loads((folder / DONE_MARKER).read_text())["sha256"]


def test_help_list_shapes_and_argument_errors(capsys):
    with pytest.raises(SystemExit) as exit_info:
        main(["--help"])
    assert exit_info.value.code == 0
    out = capsys.readouterr().out
    for option in ("--size", "--split", "--instances", "--shard", "--out", "--device", "--views", "--batch", "--seed", "--list-shapes"):
        assert option in out
    assert main(["--list-shapes"]) == 0
    records = [json.loads(line) for line in capsys.readouterr().out.splitlines()]
    assert len(records) == 60 and {r["kind"] for r in records} == {"synthetic", "everyday"}
    assert {r["split"] for r in records} == {"train", "unseen"} and all(set(r) == {"name", "kind", "split", "source"} for r in records)
    assert parse_shard("1/4") == (1, 4)
    for bad in (["--shard", "4/4"], ["--shard", "x"], ["--instances", "/nonexistent.yaml"], ["--limit", "0"],
                ["--limit", "-1"]):  # a negative --limit once dropped the last instance, silently
        with pytest.raises(SystemExit) as exit_info:
            main(bad)
        assert exit_info.value.code == 2
    err = capsys.readouterr().err
    assert "/nonexistent.yaml" in err and "--limit must be >= 1" in err
    with pytest.raises(SystemExit) as exit_info:
        main(["--device", "cuda:99", "--out", "/nonexistent/out"])  # refused before anything is written
    assert exit_info.value.code == 2
    assert "Warp device 'cuda:99' is not available" in capsys.readouterr().err


def no_simulation(monkeypatch):
    """Makes a simulation fail the test: what is checked must be found before any."""
    import ad_sim.episode

    def simulate_batch(*args, **kwargs):
        pytest.fail("simulated although the command was to be refused first")

    monkeypatch.setattr(ad_sim.episode, "simulate_batch", simulate_batch)


@pytest.mark.parametrize("bad, said", [
    (["--batch", "-1"], "--batch must be >= 1, got -1"), (["--batch", "0"], "--batch must be >= 1, got 0"),
    (["--seed", "-1"], "--seed must be >= 0, got -1"),
    (["--max-bag-size", "-5"], "--max-bag-size must be >= 0, got -5"),
    (["--max-bag-size", "1000"], "--max-bag-size must be 0 (no split) or >= 65536 bytes, got 1000"),
    (["--name", "x/../../escaped"], "--name must be a plain folder name (no / or ..), got 'x/../../escaped'"),
    (["--name", ".."], "--name must be a plain folder name"),
    (["--limit", "2", "--shards", "3"], "--shards 3: 2 instance(s) leave shard 2 of 3 empty; use at most 2 shards"),
    (["--limit", "2", "--shard", "2/3"], "--shard 2/3: 2 instance(s) leave shard 2 of 3 empty"),
    (["--instances", "BINARY"], "BINARY: not UTF-8 text ("),
    (["--views", "0"], "--views must be in 1..16, got 0"),
    (["--views", "100000000"], "--views must be in 1..16, got 100000000"),  # was taken: out of memory making cameras
], ids=["batch-negative", "batch-0", "seed", "max-bag-size", "max-bag-size-small", "name-escapes", "name-dotdot", "shards", "shard", "utf-8",
        "views-0", "views-huge"])
def test_numeric_name_and_shard_count_errors_name_the_option(bad, said, tmp_path, capsys):
    """--batch -1 once wrote an empty shard marked done (0 was the default), --shards above the instances
    an empty bag marked done, --name x/../.. wrote outside --out; --seed -1 failed in NumPy without naming
    --seed, --max-bag-size -5 or 1000 after start-up with exit 1; a non-UTF-8 instance file was not named."""
    binary = tmp_path / "binary.json"
    binary.write_bytes(b"\xff\xfe[]")
    bad, said = [str(binary) if arg == "BINARY" else arg for arg in bad], said.replace("BINARY", str(binary))
    out = tmp_path / "out"
    with pytest.raises(SystemExit) as exit_info:
        main(["--quiet", "--size", "tiny", "--split", "unseen", "--out", str(out), *bad])
    assert exit_info.value.code == 2
    err = capsys.readouterr().err
    assert said in err.splitlines()[-1], err
    assert sorted(p.name for p in tmp_path.iterdir()) == ["binary.json"]  # nothing written, in --out or beside it


def test_an_out_that_cannot_be_written_is_one_line_before_any_simulation(tmp_path, monkeypatch, capsys):
    """An --out that is a file or cannot be made, or a shard path that is a file, were tracebacks."""
    no_simulation(monkeypatch)
    args = ["--quiet", "--size", "tiny", "--split", "unseen", "--limit", "2", "--shards", "2"]
    a_file = tmp_path / "a-file"
    a_file.write_text("mine\n")
    shard_is_file = tmp_path / "shard-is-file"
    shard_is_file.mkdir()
    (shard_is_file / "unseen-1of2").write_text("mine\n")  # the second shard: found before the first is simulated
    # A shard path that links to a folder that is not there (another disk, not mounted): a link, not an absent shard
    # (taken as absent, it would fail later with "File exists", as the writer cannot make the folder)
    dangling = tmp_path / "dangling"
    dangling.mkdir()
    (dangling / "unseen-0of2").symlink_to(tmp_path / "unmounted" / "unseen-0of2")
    for out, said in ((a_file, f"error: cannot write in --out {a_file}: it is a file, not a folder"),
                      ("/proc/nope", "error: cannot write in --out /proc/nope: No such file or directory"),
                      (shard_is_file, f"error: cannot write {shard_is_file / 'unseen-1of2'}: it is a file or a link, "
                                      "not a shard folder; move it or choose another --out"),
                      (dangling, f"error: cannot write {dangling / 'unseen-0of2'}: it is a file or a link, not a shard "
                                 "folder; move it or choose another --out")):
        assert main([*args, "--out", str(out)]) == 1
        assert capsys.readouterr().err == said + "\n"
    assert a_file.read_text() == (shard_is_file / "unseen-1of2").read_text() == "mine\n"
    assert sorted(p.name for p in shard_is_file.iterdir()) == ["unseen-1of2"]
    assert sorted(p.name for p in dangling.iterdir()) == ["unseen-0of2"] and (dangling / "unseen-0of2").is_symlink()


def test_a_shard_folder_with_files_generate_does_not_write_is_not_deleted(tmp_path, monkeypatch, capsys):
    """A shard folder without a DONE marker was deleted whatever it held; now only generate's own files. A folder
    named like one of them (here unseen-0of1_2.mcap, holding a file of the user's) is not one: generate writes
    files by those names, never folders."""
    no_simulation(monkeypatch)
    shard = tmp_path / "unseen-0of1"
    shard.mkdir()
    own = ["metadata.yaml", "metadata.yaml.tmp", "unseen-0of1_0.mcap", "unseen-0of1_1.mcap", "DONE.tmp"]
    for name in [*own, "notes.txt", "other-0of1_0.mcap"]:
        (shard / name).write_text("mine\n")
    (shard / "sub").mkdir()
    (shard / "unseen-0of1_2.mcap").mkdir()
    (shard / "unseen-0of1_2.mcap" / "mine.txt").write_text("mine\n")
    assert main(["--quiet", "--size", "tiny", "--split", "unseen", "--limit", "1", "--out", str(tmp_path)]) == 1
    assert capsys.readouterr().err == (f"error: {shard} would be redone, but it holds files generate does not write "
                                       "(notes.txt, other-0of1_0.mcap, sub, unseen-0of1_2.mcap); move them or choose "
                                       "another --out\n")
    assert sorted(p.name for p in shard.iterdir()) == sorted([*own, "notes.txt", "other-0of1_0.mcap", "sub",
                                                              "unseen-0of1_2.mcap"])
    assert (shard / "unseen-0of1_2.mcap" / "mine.txt").read_text() == "mine\n"


def _interrupt_once_under_way(process, shard: Path) -> str:
    """SIGINT to a running generate once `shard` is under way (its metadata.yaml written); its output, once it has
    exited with 130."""
    deadline = time.monotonic() + 300
    while not (shard / "metadata.yaml").exists():
        assert process.poll() is None and time.monotonic() < deadline, process.stdout.read()
        time.sleep(0.02)
    process.send_signal(signal.SIGINT)
    output = process.communicate(timeout=60)[0]
    assert process.returncode == 130, output
    return output


def test_ctrl_c_says_what_to_do_without_a_traceback(tmp_path):
    interrupted = generate("--size", "tiny", "--split", "unseen", "--limit", "2", "--batch", "1",
                           "--out", str(tmp_path))
    output = _interrupt_once_under_way(interrupted, tmp_path / "unseen-0of1")
    assert "Traceback" not in output
    assert output.strip().splitlines()[-1] == (f"interrupted: {tmp_path / 'unseen-0of1'} is unfinished; run the same "
                                               "command again to redo it (finished shards are kept)")
    assert not (tmp_path / "unseen-0of1" / DONE_MARKER).exists()


def test_ctrl_c_in_a_later_shard_names_that_shard(tmp_path):
    """A Ctrl-C while the second of two shards is written names the second. Untested so far (only one shard was
    interrupted): were the list of the shard under way not emptied once a shard is done, the message would name the
    first, finished shard, sending the user to the wrong folder."""
    interrupted = generate("--size", "tiny", "--split", "unseen", "--limit", "2", "--shards", "2", "--batch", "1",
                           "--skip-particles", "--out", str(tmp_path))
    second = tmp_path / "unseen-1of2"
    output = _interrupt_once_under_way(interrupted, second)  # the first shard done, the second under way
    assert output.strip().splitlines()[-1] == (f"interrupted: {second} is unfinished; run the same command again to "
                                               "redo it (finished shards are kept)")
    assert (tmp_path / "unseen-0of2" / DONE_MARKER).is_file() and not (second / DONE_MARKER).exists()


def test_ctrl_c_before_any_shard_is_one_line_too(tmp_path, monkeypatch, capsys):
    """A Ctrl-C while the instances are drawn (or Warp starts) once escaped as a traceback."""
    import ad_sim.instances

    def interrupted(*args, **kwargs):
        raise KeyboardInterrupt

    monkeypatch.setattr(ad_sim.instances, "benchmark", interrupted)
    try:
        code = main(["--quiet", "--size", "tiny", "--split", "unseen", "--out", str(tmp_path)])
    except KeyboardInterrupt:  # a failure of this test, not a Ctrl-C of the test run
        pytest.fail("the KeyboardInterrupt escaped main")
    assert code == 130
    assert capsys.readouterr().err == ("interrupted while no shard was being written; run the same command again to "
                                       "go on (finished shards are kept)\n")
    assert list(tmp_path.iterdir()) == []


@pytest.mark.ros
def test_resume_after_kill_gives_the_uninterrupted_bags(tmp_path):
    args = ["--size", "tiny", "--split", "unseen", "--limit", "2", "--shards", "2", "--batch", "1"]
    uninterrupted = generate(*args, "--out", str(tmp_path / "a"))
    assert uninterrupted.wait(300) == 0, uninterrupted.stdout.read()

    killed = generate(*args, "--out", str(tmp_path / "b"))
    partial = tmp_path / "b" / "unseen-1of2"
    deadline = time.monotonic() + 300
    while not (partial / "metadata.yaml").exists():  # shard 0 done, shard 1 under way
        assert killed.poll() is None and time.monotonic() < deadline, killed.stdout.read()
        time.sleep(0.02)
    os.kill(killed.pid, signal.SIGKILL)
    killed.wait()
    assert (tmp_path / "b" / "unseen-0of2" / DONE_MARKER).is_file() and not (partial / DONE_MARKER).exists()

    resumed = subprocess.run(
        [str(ADRUN), "ad_sim", "generate", "--quiet", *args, "--out", str(tmp_path / "b")],
        cwd=REPO_ROOT, capture_output=True, text=True, timeout=300,
    )
    assert resumed.returncode == 0, resumed.stderr
    assert "unseen-0of2: already done, skipped" in resumed.stderr and "unseen-1of2: written" in resumed.stderr
    for shard in ("unseen-0of2", "unseen-1of2"):
        # Byte-identical .mcap files: deterministic, and the redone shard is complete.
        assert digests(tmp_path / "a" / shard) == digests(tmp_path / "b" / shard)
        assert sorted(p.name for p in (tmp_path / "b" / shard).iterdir()) == sorted([DONE_MARKER, f"{shard}_0.mcap", "metadata.yaml"])
    ids = [
        e.instance.episode_id
        for shard in ("unseen-0of2", "unseen-1of2")
        for e in group_episodes(BagReader(tmp_path / "a" / shard, topics=["/ad_sim/instance"]))
    ]
    assert sorted(ids) == ["unseen-arch-jelly-0000", "unseen-arch-plasticine-0000"]  # each in exactly one shard


@pytest.mark.ros
def test_rerun_with_other_settings_is_refused_and_keeps_the_bag(tmp_path, capsys):
    args = ["--quiet", "--size", "tiny", "--split", "unseen", "--skip-particles", "--out", str(tmp_path)]
    assert main([*args, "--limit", "1"]) == 0
    shard = tmp_path / "unseen-0of1"
    before = digests(shard)
    for same in ([], ["--views", "1"]):  # --views 1 is what unseen episodes get anyway
        assert main([*args, "--limit", "1", *same]) == 0
        assert "already done, skipped" in capsys.readouterr().err
    for other, named in ((["--limit", "2"], "instances"), (["--limit", "1", "--views", "2"], "views"),
                         (["--limit", "1", "--compression", "lz4"], "compression")):
        assert main([*args, *other]) == 1
        error = capsys.readouterr().err
        assert f"other settings ({named}" in error and "delete it or choose another --out" in error, error
    assert digests(shard) == before and sorted(p.name for p in shard.iterdir()) == sorted(
        [DONE_MARKER, "unseen-0of1_0.mcap", "metadata.yaml"])  # the finished bag is left as it was
    # A marker from before markers recorded settings cannot be compared: skipped as done, with a warning.
    marker = json.loads((shard / DONE_MARKER).read_text())
    (shard / DONE_MARKER).write_text(json.dumps({k: v for k, v in marker.items() if k != "settings"}))
    assert main([*args, "--limit", "1", "--views", "2"]) == 0
    err = capsys.readouterr().err
    assert f"warning: {shard} records no settings (an older version wrote it), so it is taken as done" in err, err
    assert "already done, skipped" in err


@pytest.mark.ros
def test_a_damaged_done_shard_is_redone_with_a_warning(tmp_path, capsys):
    """A DONE shard was skipped without a look at its files (a deleted or cut .mcap stayed broken), and a damaged
    marker was a traceback; now both are redone like an unfinished shard, saying so in one line."""
    args = ["--quiet", "--size", "tiny", "--split", "unseen", "--skip-particles", "--limit", "1", "--out", str(tmp_path)]
    assert main(args) == 0
    shard = tmp_path / "unseen-0of1"
    mcap, marker = shard / "unseen-0of1_0.mcap", shard / DONE_MARKER
    written = marker.read_text()
    sizes = json.loads(written)["sizes"]
    assert sizes == {"unseen-0of1_0.mcap": mcap.stat().st_size, "metadata.yaml": (shard / "metadata.yaml").stat().st_size}
    capsys.readouterr()

    def rerun():
        assert main(args) == 0
        lines = capsys.readouterr().err.splitlines()
        assert marker.read_text() == written and lines[-1] == f"{shard}: written", lines  # byte-identical again
        return lines[:-1]

    mcap.unlink()
    assert rerun() == [f"warning: {shard} is damaged (unseen-0of1_0.mcap is missing), so it is redone"]
    # metadata.yaml too (were only the .mcap files looked for, its size check would fail: "cannot write in --out")
    (shard / "metadata.yaml").unlink()
    assert rerun() == [f"warning: {shard} is damaged (metadata.yaml is missing), so it is redone"]
    with open(mcap, "r+b") as f:
        f.truncate(100)
    assert rerun() == [f"warning: {shard} is damaged (unseen-0of1_0.mcap has 100 bytes, not the "
                       f"{sizes['unseen-0of1_0.mcap']} it was written with), so it is redone"]
    # Settings that are not a mapping, beside intact files (unchecked, an AttributeError traceback comparing them);
    # no file's sha256: nothing to check the shard by.
    for damaged in ("", "[1, 2]", '{"settings": [1]}', written[: len(written) // 2],
                    json.dumps(json.loads(written) | {"settings": [1]}),
                    json.dumps(json.loads(written) | {"sha256": {}})):
        marker.write_text(damaged)
        assert rerun() == [f"warning: {marker} is not a marker generate writes (damaged or edited), so {shard} is "
                           "taken as unfinished and redone"], damaged
    # A marker from before sizes were recorded: checked once by its sha256s, then given the sizes.
    marker.write_text(json.dumps({k: v for k, v in json.loads(written).items() if k != "sizes"}))
    assert main(args) == 0 and capsys.readouterr().err == f"{shard}: already done, skipped\n"
    assert json.loads(marker.read_text())["sizes"] == sizes
    # With the sizes, a finished shard is checked by them alone, not read again (gigabytes at full scale, on every
    # re-run): a file of the same size with other bytes is left to a full check (sha256sum against the marker).
    recorded = marker.read_text()
    data = bytearray(mcap.read_bytes())
    data[len(data) // 2] ^= 0xFF  # the same size, other bytes
    mcap.write_bytes(bytes(data))
    assert main(args) == 0 and capsys.readouterr().err == f"{shard}: already done, skipped\n"
    assert marker.read_text() == recorded
    marker.write_text(json.dumps({k: v for k, v in json.loads(written).items() if k != "sizes"}))
    assert rerun() == [f"warning: {shard} is damaged (unseen-0of1_0.mcap is not the file it was written as "
                       "(sha256)), so it is redone"]
    assert main(args) == 0 and capsys.readouterr().err == f"{shard}: already done, skipped\n"


@pytest.mark.ros
def test_a_later_shard_that_would_be_refused_is_refused_before_any_simulation(tmp_path, monkeypatch, capsys):
    """A finished shard written with other settings, or damaged and holding a user's file, was refused only
    when its turn came, after the shards before it had been simulated (hours, at full scale)."""
    args = ["--quiet", "--size", "tiny", "--split", "unseen", "--skip-particles", "--limit", "2", "--shards", "2",
            "--out", str(tmp_path)]
    assert main(args) == 0
    first, second = tmp_path / "unseen-0of2", tmp_path / "unseen-1of2"
    shutil.rmtree(first)
    before = digests(second)
    no_simulation(monkeypatch)
    capsys.readouterr()
    assert main([*args, "--compression", "lz4"]) == 1
    assert f"{second} was written with other settings (compression)" in capsys.readouterr().err
    (second / "unseen-1of2_0.mcap").unlink()
    (second / "notes.txt").write_text("mine")
    assert main(args) == 1
    assert f"error: {second} would be redone, but it holds files generate does not write (notes.txt)" in \
        capsys.readouterr().err
    assert not first.exists() and (second / "notes.txt").read_text() == "mine" and digests(second) == before


@pytest.mark.ros
def test_what_decides_a_shards_content_is_compared_and_batches_number_episodes_on(tmp_path, monkeypatch, capsys):
    """A finished shard is skipped only when asked for with the settings it was written with. Editing a parameter
    of an instance file, leaving out --skip-particles or adding --max-bag-size changes the bags: each is refused
    before any simulation, naming it. Untested so far (the other settings were): a marker whose settings left one of
    them out would make a re-run say "already done, skipped" and keep bags of the old settings. And a shard
    simulated in several batches (--batch 1 here; 8 episodes a batch is the default on the CPU) numbers its episodes
    on from batch to batch; untested too (every test shard was one batch): numbered from 0 in each batch, they would
    be stamped alike, and readers would take them for several simulator runs recorded into one bag and leave them
    all out."""
    entries = [
        {"shape": "cone", "material": "jelly", "seed": 5,
         "parameters": {"youngs_modulus": 1.0e5, "poissons_ratio": 0.3}},
        {"shape": "box", "material": "sand", "seed": 7, "parameters": {"friction_angle": 0.4}},
    ]
    path = tmp_path / "mine.yaml"
    path.write_text(yaml.safe_dump(entries))
    without_skip = ["--quiet", "--instances", str(path), "--batch", "1", "--out", str(tmp_path / "out")]
    args = [*without_skip, "--skip-particles"]
    assert main(args) == 0
    shard = tmp_path / "out" / "mine-0of1"
    from ad_sim.rosbag import distinct_episodes

    collided = []
    episodes = list(distinct_episodes(group_episodes(BagReader(shard)), lambda group, reason: collided.append(reason)))
    assert not collided
    assert [(e.instance.episode_index, e.instance.shape) for e in episodes] == [(0, "cone"), (1, "box")]
    assert episodes[1].stamp_ns == messages.frame_stamp(1, 0) > episodes[0].stamp_ns
    before = digests(shard)
    capsys.readouterr()
    no_simulation(monkeypatch)
    assert main(args) == 0 and "already done, skipped" in capsys.readouterr().err
    original = path.read_text()
    entries[0]["parameters"]["youngs_modulus"] = 2.0e5
    edited = yaml.safe_dump(entries)
    for text, run, named in ((edited, args, "instances (split, seed, --limit or file)"),
                             (original, without_skip, "skip"),
                             (original, [*args, "--max-bag-size", "65536"], "max_bag_size")):
        path.write_text(text)
        assert main(run) == 1
        error = capsys.readouterr().err
        assert f"error: {shard} was written with other settings ({named}); delete it" in error, error
    assert digests(shard) == before


def shard_masks(shard):
    """{(episode_id, stamp): mono8 pixels} of every mask frame of a bag folder."""
    out = {}
    for episode in group_episodes(BagReader(shard)):
        for topic, frames in episode.messages.items():
            if topic.endswith("/mask"):
                for stamp, image in frames:
                    assert image.encoding == "mono8" and (image.height, image.width) == (128, 128)
                    out[episode.instance.episode_id, topic, stamp] = np.frombuffer(bytes(image.data), np.uint8)
    return out


@pytest.mark.ros
def test_coverage_masks_are_grey_threshold_to_the_binary_masks_and_are_a_setting(tmp_path, capsys):
    args = ["--quiet", "--size", "tiny", "--split", "unseen", "--skip-particles", "--limit", "1"]
    binary, grey = tmp_path / "binary", tmp_path / "grey"
    assert main([*args, "--out", str(binary)]) == 0
    assert main([*args, "--coverage-masks", "--out", str(grey)]) == 0
    capsys.readouterr()
    binary_shard, grey_shard = binary / "unseen-0of1", grey / "unseen-0of1"
    assert digests(binary_shard) != digests(grey_shard)
    binary_masks, grey_masks = shard_masks(binary_shard), shard_masks(grey_shard)
    assert len(binary_masks) == 25 and binary_masks.keys() == grey_masks.keys()  # the same episode, frames and stamps
    levels = set()
    for key, mask in binary_masks.items():
        assert set(np.unique(mask)) <= {0, 255}
        np.testing.assert_array_equal(grey_masks[key] > 127, mask == 255, err_msg=str(key))
        levels |= set(np.unique(grey_masks[key]).tolist())
    assert len(levels - {0, 255}) > 10  # grey edges, of many coverages
    # Only the masks differ: the ground truth and camera messages are the same.
    for a, b in zip(group_episodes(BagReader(binary_shard)), group_episodes(BagReader(grey_shard))):
        assert as_plain(a.instance) == as_plain(b.instance)
        assert as_plain(a.messages["/ad_sim/view_0/camera_info"]) == as_plain(b.messages["/ad_sim/view_0/camera_info"])
    # The markers and the bags' metadata say which masks they hold (absent: binary, as before the option).
    settings = {name: json.loads((shard / DONE_MARKER).read_text())["settings"]
                for name, shard in (("binary", binary_shard), ("grey", grey_shard))}
    assert "masks" not in settings["binary"] and settings["grey"]["masks"] == "coverage"
    assert {k: v for k, v in settings["grey"].items() if k != "masks"} == settings["binary"]
    custom = {name: yaml.safe_load((shard / "metadata.yaml").read_text())["rosbag2_bagfile_information"]["custom_data"]
              for name, shard in (("binary", binary_shard), ("grey", grey_shard))}
    assert "masks" not in custom["binary"] and custom["grey"]["masks"] == "coverage"
    before = {shard: digests(shard) for shard in (binary_shard, grey_shard)}
    # The same request again: done; the other kind of masks into either folder: refused, naming masks.
    for out, same, other in ((binary, [], ["--coverage-masks"]), (grey, ["--coverage-masks"], [])):
        assert main([*args, *same, "--out", str(out)]) == 0
        assert "already done, skipped" in capsys.readouterr().err
        assert main([*args, *other, "--out", str(out)]) == 1
        error = capsys.readouterr().err
        assert f"{out / 'unseen-0of1'} was written with other settings (masks); delete it or choose another --out" \
            in error, error
    assert {shard: digests(shard) for shard in before} == before  # both bags left as they were
    # A marker with settings but no masks key (every marker before the option) matches a default request.
    marker = json.loads((grey_shard / DONE_MARKER).read_text())
    marker["settings"].pop("masks")
    (grey_shard / DONE_MARKER).write_text(json.dumps(marker))
    assert main([*args, "--out", str(grey)]) == 0
    assert "already done, skipped" in capsys.readouterr().err
    assert main([*args, "--coverage-masks", "--out", str(grey)]) == 1
    assert "other settings (masks)" in capsys.readouterr().err


@pytest.mark.ros
def test_instance_file_one_shard_and_skip_particles(tmp_path):
    entries = [
        {"shape": "cone", "material": "plasticine", "seed": 5,
         "parameters": {"youngs_modulus": 1.0e5, "poissons_ratio": 0.4, "yield_stress": 2000.0}},
        {"shape": "capsule", "material": "jelly", "seed": 6, "parameters": {"youngs_modulus": 5.0e4, "poissons_ratio": 0.25}},
        {"shape": "box", "material": "sand", "seed": 7, "parameters": {"friction_angle": 0.4}},
    ]
    path = tmp_path / "mine.yaml"
    path.write_text(yaml.safe_dump(entries))
    run = generate("--instances", str(path), "--shard", "1/2", "--views", "2", "--skip-particles", "--out", str(tmp_path / "out"))
    assert run.wait(300) == 0, run.stdout.read()
    said = [line for line in run.stdout.read().splitlines() if not line.startswith("Warp CUDA warning")]  # no GPU here
    assert said == [f"{tmp_path / 'out' / 'mine-1of2'}: written"], said  # --quiet: no Warp banner or module lines
    assert sorted(p.name for p in (tmp_path / "out").iterdir()) == ["mine-1of2"]  # only the shard asked for
    bag = tmp_path / "out" / "mine-1of2"
    topics = BagReader(bag).topics()
    assert messages.particles_topic() not in topics and "/ad_sim/view_1/mask" in topics
    episodes = list(group_episodes(BagReader(bag)))
    assert [e.instance.shape for e in episodes] == ["capsule"]  # entries 1, 3, ... of the file
    instance = episodes[0].instance
    assert (instance.material, list(instance.parameters), instance.seed) == ("jelly", [5.0e4, 0.25], 6)
    assert len(instance.camera_poses) == 2 and instance.episode_index == 0
    masks = episodes[0].messages["/ad_sim/view_1/mask"]
    assert [stamp for stamp, _ in masks] == [messages.frame_stamp(0, t) for t in range(25)]
    assert all(set(m.data) <= {0, 255} for _, m in masks) and any(255 in m.data for _, m in masks)


def test_committed_sample_bags():
    """bags/samples: unseen shapes, every family, one view, 25 frames, small (bags/README.md)."""
    from ad_sim.instances import benchmark_shapes
    from ad_sim.shapes import list_shapes

    samples = REPO_ROOT / "bags" / "samples"
    bags = sorted(p for p in samples.iterdir() if (p / "metadata.yaml").is_file())
    assert [b.name for b in bags] == ["unseen-masks-0of1", "unseen-particles-0of1"]
    assert sum(f.stat().st_size for b in bags for f in b.iterdir()) < 3.2e6
    unseen = {info.name for info in list_shapes("unseen")}
    families = set()
    for bag in bags:
        assert (bag / DONE_MARKER).is_file()
        episodes = list(group_episodes(BagReader(bag)))
        for episode in episodes:
            instance = episode.instance
            assert instance.split == "unseen" and instance.shape in unseen and len(instance.camera_poses) == 1
            families.add(instance.material)
            assert len(episode.messages["/ad_sim/view_0/mask"]) == len(episode.messages["/ad_sim/view_0/camera_info"]) == 25
            if bag.name == "unseen-particles-0of1":
                clouds = episode.messages["/ad_sim/particles"]
                assert len(clouds) == 25 and all(c.width == 1024 and c.point_step == 60 for _, c in clouds)
    assert families == {"jelly", "plasticine", "sand"}
    # The independent reader too, with the types from the bags' own schemas.
    for bag in bags:
        typestore = get_typestore(Stores.EMPTY)
        with AnyReader([bag], default_typestore=typestore) as reader:
            for connection in reader.connections:
                typestore.register(get_types_from_msg(connection.msgdef.data, connection.msgtype))
            names = [
                typestore.deserialize_cdr(data, connection.msgtype).shape
                for connection, _, data in reader.messages(connections=[c for c in reader.connections if c.topic == "/ad_sim/instance"])
            ]
        assert names == [e.instance.shape for e in group_episodes(BagReader(bag, topics=["/ad_sim/instance"]))]
    masks_bag = [e.instance.shape for e in group_episodes(BagReader(bags[0], topics=["/ad_sim/instance"]))]
    assert sorted(set(masks_bag)) == sorted(benchmark_shapes("unseen", "tiny")) and len(masks_bag) == 6


def test_generate_starts_without_warp_so_an_early_ctrl_c_is_one_line():
    """Importing the command pulls in neither Warp nor SciPy (a second of imports): a Ctrl-C right after
    start then lands in main's handler (one line, exit 130), not in a module import's traceback."""
    probe = "import sys, ad_sim.generate; print(sorted({'warp', 'scipy', 'trimesh'} & set(sys.modules)))"
    result = subprocess.run([sys.executable, "-c", probe], capture_output=True, text=True, timeout=60)
    assert result.returncode == 0 and result.stdout.strip() == "[]", result.stdout + result.stderr


def test_write_instances_gives_a_template_that_reads_back_as_the_split(tmp_path, capsys):
    """A user's own scenes start from a benchmark split's instances, written as an instance file."""
    from dataclasses import replace

    from ad_sim.instances import benchmark, load_instance_file

    out = tmp_path / "mine.yaml"
    assert main(["--size", "tiny", "--split", "unseen", "--limit", "3", "--views", "2", "--write-instances", str(out),
                 "--out", str(tmp_path / "bags")]) == 0
    assert load_instance_file(out) == [replace(i, views=2) for i in benchmark("tiny", "unseen", 0)[:3]]
    assert not (tmp_path / "bags").exists()  # nothing simulated
    assert main(["--size", "tiny", "--write-instances", str(out)]) == 1  # an edited file is not overwritten
    assert "exists; delete it or pass another file name" in capsys.readouterr().err
