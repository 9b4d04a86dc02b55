"""ad_sim.rosbag: rosbag2 layout, schemas, round trips, splitting, independent reader, errors."""

from __future__ import annotations

import errno
import os
import re
import shutil
import signal
import subprocess
import sys
import textwrap
import warnings
from pathlib import Path

import numpy as np
import pytest
import yaml
from mcap.reader import make_reader
from mcap.writer import Writer
from rosbags.highlevel import AnyReader
from rosbags.typesys import Stores, get_typestore, get_types_from_msg
from sim_fixtures import as_plain, fabricated_episode

from ad_sim import messages, rosbag
from ad_sim.generate import write_episodes
from ad_sim.rosbag import BagError, BagReader, BagWriter, group_episodes

DELIMITER = "=" * 80


def write_fabricated_bag(path: Path, episodes: int = 2, views: int = 1, **writer_options) -> list[tuple[str, int, dict]]:
    """A bag of fabricated episodes; returns what was written, in order."""
    eps = [fabricated_episode(seed, views, material=("jelly", "plasticine", "sand")[seed % 3]) for seed in range(episodes)]
    with BagWriter(path, **writer_options) as writer:
        write_episodes(writer, eps, 0)
    return [item for index, episode in enumerate(eps) for item in messages.episode_messages(episode, index)]


@pytest.fixture(scope="module")
def bag(tmp_path_factory) -> tuple[Path, list]:
    path = tmp_path_factory.mktemp("bags") / "two"
    return path, write_fabricated_bag(path, episodes=2, views=2)


@pytest.mark.ros
def test_vendored_schemas_equal_installed_interfaces():
    """ad_sim/data/schemas (python -m ad_sim.rosbag vendor-schemas) equal the built interfaces."""
    for type_name in rosbag.VENDORED_TYPES:
        vendored = rosbag.load_schema(type_name)
        assert vendored.definition == rosbag.build_message_definition(type_name)
        assert vendored.type_hash == rosbag.installed_type_hash(type_name)
        assert vendored.type_hash.startswith("RIHS01_") and len(vendored.type_hash) == 7 + 64


def test_definitions_carry_every_dependency_once():
    definition = rosbag.load_schema("ad_msgs/msg/SimInstance").definition
    names = [line[5:] for line in definition.splitlines() if line.startswith("MSG: ")]
    assert sorted(names) == sorted(
        ["geometry_msgs/Pose", "geometry_msgs/Point", "geometry_msgs/Quaternion", "geometry_msgs/Twist",
         "geometry_msgs/Vector3", "std_msgs/Header", "builtin_interfaces/Time"]
    )
    lines = definition.splitlines()
    for i, line in enumerate(lines):
        if line.startswith("MSG: "):
            assert lines[i - 1] == DELIMITER
    assert not lines[0].startswith("MSG")  # the top-level type comes first, without delimiter
    assert rosbag.starts_with_header(definition)


def test_metadata_yaml_is_rosbag2_format_9(bag):
    path, written = bag
    info = yaml.safe_load((path / "metadata.yaml").read_text())["rosbag2_bagfile_information"]
    assert info["version"] == 9 and info["storage_identifier"] == "mcap" and info["ros_distro"] == "jazzy"
    assert info["relative_file_paths"] == ["two_0.mcap"] and info["files"][0]["path"] == "two_0.mcap"
    assert info["message_count"] == len(written) == info["files"][0]["message_count"]
    stamps = [stamp for _, stamp, _ in written]
    assert info["starting_time"]["nanoseconds_since_epoch"] == min(stamps)
    assert info["duration"]["nanoseconds"] == max(stamps) - min(stamps)
    topics = {t["topic_metadata"]["name"]: t for t in info["topics_with_message_count"]}
    assert set(topics) == set(messages.topic_types(2))
    instance = topics["/ad_sim/instance"]
    assert instance["message_count"] == 2
    assert instance["topic_metadata"]["type"] == "ad_msgs/msg/SimInstance"
    assert instance["topic_metadata"]["serialization_format"] == "cdr"
    assert instance["topic_metadata"]["type_description_hash"] == rosbag.load_schema("ad_msgs/msg/SimInstance").type_hash
    qos = instance["topic_metadata"]["offered_qos_profiles"][0]
    assert qos["durability"] == "transient_local" and qos["reliability"] == "reliable"
    assert topics["/ad_sim/particles"]["topic_metadata"]["offered_qos_profiles"][0]["durability"] == "volatile"
    assert topics["/ad_sim/particles"]["message_count"] == 50
    assert "compression_format" in info and "compression_mode" in info and "custom_data" in info


def test_mcap_records_are_what_rosbag2_writes(bag):
    path, _ = bag
    with open(path / "two_0.mcap", "rb") as f:
        reader = make_reader(f)
        assert reader.get_header().profile == "ros2"
        summary = reader.get_summary()
        assert {s.name for s in summary.schemas.values()} == set(rosbag.VENDORED_TYPES)
        assert {s.encoding for s in summary.schemas.values()} == {"ros2msg"}
        for channel in summary.channels.values():
            assert channel.message_encoding == "cdr"
            profiles = yaml.safe_load(channel.metadata["offered_qos_profiles"])
            assert profiles[0]["reliability"] == "reliable"
            assert channel.metadata["topic_type_hash"] == rosbag.load_schema(summary.schemas[channel.schema_id].name).type_hash
        assert summary.chunk_indexes and {c.compression for c in summary.chunk_indexes} == {"zstd"}
        stored = {m.name: m.metadata for m in reader.iter_metadata()}
        assert yaml.safe_load(stored["rosbag2"]["serialized_metadata"])["version"] == 9


def test_round_trip_decodes_to_the_written_dicts_in_log_time_order(bag):
    path, written = bag
    read = list(BagReader(path))
    assert [(t, s) for t, s, _ in read] == [(t, s) for t, s, _ in written]
    for (_, _, decoded), (_, _, original) in zip(read, written):
        assert as_plain(decoded) == as_plain(original)
    raw = list(BagReader(path, raw=True, topics=["/ad_sim/instance"]))
    assert len(raw) == 2 and all(isinstance(m.message, bytes) for m in raw)


def test_split_by_size_and_read_back_across_files(tmp_path):
    path = tmp_path / "split"
    written = write_fabricated_bag(path, episodes=2, views=1, max_bag_size=300_000, chunk_size=100_000)
    files = sorted(path.glob("*.mcap"))
    assert len(files) >= 3
    info = yaml.safe_load((path / "metadata.yaml").read_text())["rosbag2_bagfile_information"]
    assert info["relative_file_paths"] == [f"split_{i}.mcap" for i in range(len(files))]
    assert sum(f["message_count"] for f in info["files"]) == len(written)
    assert all(f.stat().st_size < 300_000 + 200_000 for f in files)
    read = list(BagReader(path, raw=True))
    assert [(t, s) for t, s, _ in read] == [(t, s) for t, s, _ in written]
    # what `ros2 bag info` shows: the bag's and each file's first log time and span
    stamps = sorted(s for _, s, _ in written)
    assert info["starting_time"]["nanoseconds_since_epoch"] == stamps[0]
    assert info["duration"]["nanoseconds"] == stamps[-1] - stamps[0]
    for entry, file in zip(info["files"], files):
        own = [m.log_time_ns for m in BagReader(file, raw=True)]
        assert entry["starting_time"]["nanoseconds_since_epoch"] == min(own)
        assert entry["duration"]["nanoseconds"] == max(own) - min(own)


def test_split_files_exceed_max_bag_size_by_at_most_a_small_chunk(tmp_path):
    """As rosbag2, a file is closed once it has reached max_bag_size. Chunks were 1 MiB whatever the limit, so a 64 KiB
    limit gave files of over 1 MiB; chunks are now at most an eighth of the limit (or one message, where larger), and
    every message is read back once, in order."""
    rng = np.random.default_rng(0)
    limit = rosbag.MIN_SPLIT_SIZE
    payloads = [bytes(4) + rng.bytes(int(n)) for n in rng.integers(100, 3000, 300)]  # incompressible
    path = tmp_path / "bag"
    with BagWriter(path, max_bag_size=limit) as writer:
        writer.add_topic("/p", "sensor_msgs/msg/PointCloud2")
        for stamp, payload in enumerate(payloads):
            writer.write("/p", stamp, payload)
    sizes = [f.stat().st_size for f in sorted(path.glob("*.mcap"))]
    assert len(sizes) >= 5 and max(sizes) <= limit + limit // 8 + 3000 + 4096, sizes  # + a message, the summary
    assert [m.message for m in BagReader(path, raw=True)] == payloads


def test_reader_orders_by_log_time_across_chunks(tmp_path):
    path = tmp_path / "unordered"
    schema = rosbag.load_schema("sensor_msgs/msg/Image")
    stamps = [5, 1, 4, 2, 3, 0, 9, 7, 8, 6] * 3
    with BagWriter(path, chunk_size=1) as writer:  # one message per chunk
        writer.add_topic("/a", schema.name)
        for i, stamp in enumerate(stamps):
            writer.write("/a", stamp, messages.mask_message(np.full((1, 1), i, np.uint8), stamp, "f"))
    read = list(BagReader(path))
    assert [s for _, s, _ in read] == sorted(stamps)
    # ties keep file order
    assert [m.message.data[0] for m in read if m.log_time_ns == 5] == [i for i, s in enumerate(stamps) if s == 5]


def write_killed_bag(path: Path, stamps: list[int]) -> None:
    """A bag whose writer was killed (no summary), one message per chunk on /a, the i-th stamped stamps[i]."""
    writer = BagWriter(path, chunk_size=1)  # one message per chunk
    writer.add_topic("/a", "sensor_msgs/msg/Image")
    for i, stamp in enumerate(stamps):
        writer.write("/a", stamp, messages.mask_message(np.full((1, 1), i, np.uint8), stamp, "f"))
    writer._stream.close()  # never closed: no summary, as after a kill -9


def count_decompressions(monkeypatch) -> list:
    """A list that grows by one each time the reader decompresses a chunk."""
    decompressed = []
    breakup_chunk = rosbag.breakup_chunk
    monkeypatch.setattr(rosbag, "breakup_chunk", lambda *a, **k: decompressed.append(1) or breakup_chunk(*a, **k))
    return decompressed


def test_a_killed_writers_file_is_read_chunk_by_chunk_in_log_time_order(tmp_path, monkeypatch):
    """A file without a summary (a killed recorder's): every message of it was decompressed and held before the
    first was yielded, so recovering (or repairing) a large unsplit recording needed memory for all of it (369 MB
    resident to read a 36 MB file of 300 MB of messages, 58 MB once closed). Now the chunks' start times come from
    their messages, read in a first pass one chunk at a time (their headers are covered by no CRC), and messages are
    released as the chunks are read again, as with a summary, in the same order."""
    path = tmp_path / "killed"
    stamps = [i * 10 + (15 if i % 3 == 1 else 0) for i in range(60)]  # out of order from chunk to chunk
    write_killed_bag(path, stamps)
    decompressed = count_decompressions(monkeypatch)
    with pytest.warns(UserWarning, match="truncated"):
        read = iter(BagReader(path, recover=True))
        first = next(read)
        assert first.log_time_ns == 0 and len(decompressed) < len(stamps) + 5  # the first pass, then < 5 chunks
        rest = list(read)
    assert [m.log_time_ns for m in [first, *rest]] == sorted(stamps)
    assert [m.message.data[0] for m in [first, *rest]] == sorted(range(60), key=lambda i: stamps[i])


def test_topics_then_reading_walk_a_killed_writers_file_once_each(tmp_path, monkeypatch):
    """training/data.py asks topics() before it reads a bag. Of a file without a summary, both walked all the records
    (decompressing every chunk), and reading walked them twice (its first pass learns each chunk's start time): three
    walks. The reader keeps what a walk learned: reading after topics() walks the file once, to yield the messages."""
    path = tmp_path / "killed"
    stamps = [i * 10 + (15 if i % 3 == 1 else 0) for i in range(60)]
    write_killed_bag(path, stamps)
    decompressed = count_decompressions(monkeypatch)
    reader = BagReader(path, recover=True)
    with pytest.warns(UserWarning, match="truncated"):
        assert reader.topics() == {"/a": "sensor_msgs/msg/Image"}
        walk = len(decompressed)
        assert [m.log_time_ns for m in reader] == sorted(stamps)
        assert walk == len(stamps) and len(decompressed) == 2 * walk, f"{len(decompressed) / walk} walks"
        assert reader.topics() == {"/a": "sensor_msgs/msg/Image"} and len(decompressed) == 2 * walk  # no walk
        assert [m.log_time_ns for m in reader] == sorted(stamps) and len(decompressed) == 3 * walk


@pytest.mark.parametrize("closed", [False, True], ids=["still-writing", "closed-since"])
def test_a_file_that_grew_since_an_earlier_pass_is_learnt_anew(tmp_path, closed):
    """A recorder still writing (`info`, `replay --recover` or `repair` of a bag being recorded): topics() walked the
    file as it was, and reading it once it had grown used that walk's chunk start times, which know nothing of the
    chunks written since: a message of a later chunk logged before those of an earlier one came out of log-time order,
    with a warning blaming "the summary's chunk indexes" of a file without a summary. And once the recorder had closed
    the file, reading it still said it was truncated. What a pass learns is kept only while the file keeps its size."""
    path = tmp_path / "live"
    stamps = [0, 10, 20, 30, 15, 40]  # the fifth message (chunk) is logged before the fourth
    file = path / "live_0.mcap"
    writer = BagWriter(path, chunk_size=1)  # one message per chunk, each on disk as it is written
    writer.add_topic("/a", "sensor_msgs/msg/Image")
    sizes = []
    for i, stamp in enumerate(stamps):
        writer.write("/a", stamp, messages.mask_message(np.full((1, 1), i, np.uint8), stamp, "f"))
        sizes.append(file.stat().st_size)
    writer.close() if closed else writer._stream.close()  # closed: with its summary; else as a kill leaves it
    whole = file.read_bytes()
    file.write_bytes(whole[: sizes[3]])  # the file when the first four chunks were written
    reader = BagReader(path, recover=True)
    with pytest.warns(UserWarning, match="truncated"):
        assert reader.topics() == {"/a": "sensor_msgs/msg/Image"}
    file.write_bytes(whole)  # written on since
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        assert [m.log_time_ns for m in reader] == sorted(stamps)
    unexpected = [str(w.message) for w in caught if "read late" in str(w.message) or closed]
    assert not unexpected, unexpected


def test_independent_reader_decodes_with_types_from_the_bag(bag):
    path, written = bag
    typestore = get_typestore(Stores.EMPTY)
    with AnyReader([path], default_typestore=typestore) as reader:
        for connection in reader.connections:
            # Register the types from the definitions embedded in the bag, nothing else.
            typestore.register(get_types_from_msg(connection.msgdef.data, connection.msgtype))
        expected = iter(written)
        count = 0
        for connection, timestamp, data in reader.messages():
            topic, stamp, original = next(expected)
            assert (connection.topic, timestamp) == (topic, stamp)
            decoded = typestore.deserialize_cdr(data, connection.msgtype)
            assert as_plain(decoded) == as_plain(original)
            count += 1
        assert count == len(written)


def test_group_episodes_assigns_frames_by_stamp(bag):
    path, _ = bag
    episodes = list(group_episodes(BagReader(path)))
    assert [e.instance.episode_index for e in episodes] == [0, 1]
    for episode in episodes:
        assert len(episode.messages["/ad_sim/particles"]) == 25
        assert len(episode.messages["/ad_sim/view_1/mask"]) == 25
        assert episode.messages["/ad_sim/particles"][0][0] == episode.stamp_ns
    # A recorder may store frame 0 of an episode before its instance message (same stamp).
    stream = list(BagReader(path))
    second = next(i for i, m in enumerate(stream) if m.topic == "/ad_sim/instance" and m.log_time_ns > 0)
    stream.insert(second + 3, stream.pop(second))
    regrouped = list(group_episodes(stream))
    assert [len(e.messages["/ad_sim/view_0/mask"]) for e in regrouped] == [25, 25]
    # Later than frame 0: the instance after two frames of each topic (five topics a frame), which move with it, in
    # their order (they are taken off the end, frame 1 first: put back in the other order, frame 1 came first).
    stream = list(BagReader(path))
    stream.insert(second + 10, stream.pop(second))
    assert stream[second + 9].log_time_ns > stream[second].log_time_ns  # frame 1 precedes the instance now
    regrouped = list(group_episodes(stream))
    assert [len(e.messages["/ad_sim/view_0/mask"]) for e in regrouped] == [25, 25]
    for episode in regrouped:
        for topic, items in episode.messages.items():
            stamps = [stamp for stamp, _ in items]
            assert stamps == sorted(stamps) and stamps[0] == episode.stamp_ns, topic
    # The first episode's too (they were dropped as messages from before any instance); a recording that
    # started mid-episode still drops what came before its first instance.
    stream = list(BagReader(path))
    stream.insert(3, stream.pop(0))
    assert stream[0].topic != "/ad_sim/instance" and stream[3].topic == "/ad_sim/instance"
    regrouped = list(group_episodes(stream))
    assert [len(e.messages["/ad_sim/view_0/mask"]) for e in regrouped] == [25, 25]
    assert [len(e.messages["/ad_sim/particles"]) for e in regrouped] == [25, 25]
    late_start = [m for m in BagReader(path) if m.log_time_ns > 0.1e9]  # first instance at the next episode
    assert len(list(group_episodes(late_start))) == 1


# ------------------------------------------------------------------------------- errors


def test_missing_and_empty_bags_are_clear_errors(tmp_path):
    with pytest.raises(BagError, match="does not exist"):
        BagReader(tmp_path / "nope")
    (tmp_path / "empty").mkdir()
    with pytest.raises(BagError, match=r"no .mcap file$"):
        BagReader(tmp_path / "empty")
    # A folder of bags is not a bag: the message names the ones in it (replay takes one)
    for name in ("b", "a/x"):
        (tmp_path / "empty" / name).mkdir(parents=True)
        (tmp_path / "empty" / name / "bag_0.mcap").write_bytes(b"")
    with pytest.raises(BagError, match=r"holds no .mcap file; the bags in it: a/x, b \(pass one\)"):
        BagReader(tmp_path / "empty")
    (tmp_path / "text.mcap").write_text("hello, this is not mcap")
    for read in (list, BagReader.topics):  # reading messages, or only the summary (replay does)
        with pytest.raises(BagError, match="not an MCAP file"):
            read(BagReader(tmp_path / "text.mcap", recover=True))
    with pytest.raises(BagError, match="already exists"):
        BagWriter(tmp_path)  # not empty


def test_truncated_file_is_an_error_and_recoverable(tmp_path):
    path = tmp_path / "trunc"
    written = write_fabricated_bag(path, episodes=2, chunk_size=50_000)
    file = path / "trunc_0.mcap"
    data = file.read_bytes()
    file.write_bytes(data[: len(data) // 2])
    with pytest.raises(BagError, match=r"trunc_0\.mcap is truncated") as refused:
        list(BagReader(path))
    # The message names the flag of the command lines; the Python equivalent is a note (shown in tracebacks).
    assert str(refused.value).endswith("Read every complete chunk of it with --recover"), refused.value
    assert refused.value.__notes__ == ["In Python: BagReader(path, recover=True) reads what is readable."]
    reader = BagReader(path, recover=True)
    with pytest.warns(UserWarning) as caught:
        topics = reader.topics()  # scans the summary-less file (replay asks first) ...
        recovered = list(reader)  # ... and reading scans it again
    assert 0 < len(recovered) < len(written)
    # What is recovered is exactly a prefix of what was written.
    assert [(t, s) for t, s, _ in recovered] == [(t, s) for t, s, _ in written[: len(recovered)]]
    assert set(topics) == {t for t, _, _ in written}
    # Said once, as what was recovered and lost (no advice to use --recover, which is in use).
    (warning,) = [str(w.message) for w in caught]
    assert reader.problems == [warning]
    assert warning.startswith(f"{file} is truncated: no MCAP footer ({len(data) // 2} bytes")
    assert f"recovered {len(recovered)} messages; the last " in warning and "--recover" not in warning


def test_empty_or_magic_only_file_is_truncated_not_foreign(tmp_path):
    """A writer killed as it created a file leaves nothing, part of the magic or the magic alone: truncated, not
    foreign. Alone, it leaves nothing to recover, which is an error saying so; beside a readable file, a warning, and
    topics() (which replay asks first) lists the readable file's topics: the file read through its summary only is
    not taken for one without messages."""
    written = write_fabricated_bag(tmp_path / "split", episodes=1)
    for name, content, what in (("empty", b"", "is empty"), ("cut", rosbag.MCAP_MAGIC[:4], "is truncated inside the MCAP magic (4 bytes")):
        file = tmp_path / f"{name}.mcap"
        file.write_bytes(content)
        with pytest.raises(BagError, match=rf"{name}\.mcap {re.escape(what)}.*--recover"):
            list(BagReader(file))
        for read in (list, BagReader.topics):
            with pytest.raises(rosbag.BagUnreadable, match=rf"^nothing readable in {re.escape(str(file))}: it {re.escape(what)}"):
                read(BagReader(file, recover=True))
        (tmp_path / "split" / "split_1.mcap").write_bytes(content)  # the next file of a split bag
        with pytest.warns(UserWarning, match=r"reading \.mcap files not named in metadata\.yaml: split_1\.mcap"), \
                pytest.warns(UserWarning, match=rf"split_1\.mcap {re.escape(what)}.*: recovered 0 messages$"):
            assert len(list(BagReader(tmp_path / "split", recover=True))) == len(written)
        with pytest.warns(UserWarning, match=r"split_1\.mcap"):
            assert set(BagReader(tmp_path / "split", recover=True).topics()) == set(messages.topic_types(1))
    # The magic and nothing after it: too short for a footer, so truncated (without the length check, the footer's
    # place would lie before the start of the 8-byte file: an IndexError, not a word of what is wrong).
    file = tmp_path / "magic.mcap"
    file.write_bytes(rosbag.MCAP_MAGIC)
    with pytest.raises(rosbag.BagDamaged, match=r"magic\.mcap is truncated: no MCAP footer \(8 bytes.*--recover"):
        list(BagReader(file))
    with pytest.raises(rosbag.BagUnreadable, match=r"it is truncated before its first complete chunk \(8 bytes"):
        list(BagReader(file, recover=True))


def test_damage_before_the_first_complete_chunk_leaves_nothing_to_recover(tmp_path, capsys):
    """A file cut inside its first chunk, or whose every chunk is corrupt: recovering reads no message,
    which is said as such (not as a bag without topics), and `repair` fails without leaving a bag."""
    write_fabricated_bag(tmp_path / "cut", episodes=1)
    file = tmp_path / "cut" / "cut_0.mcap"
    file.write_bytes(file.read_bytes()[:300])
    message = rf"^nothing readable in {re.escape(str(file))}: it is truncated before its first complete chunk \(300 bytes"
    for read in (list, BagReader.topics):
        with pytest.raises(rosbag.BagUnreadable, match=message):
            read(BagReader(tmp_path / "cut", recover=True))
    write_fabricated_bag(tmp_path / "corrupt", episodes=1, chunk_size=50_000)
    file = tmp_path / "corrupt" / "corrupt_0.mcap"
    with open(file, "rb") as f:
        chunks = make_reader(f).get_summary().chunk_indexes
    data = bytearray(file.read_bytes())
    for chunk in chunks:
        middle = chunk.chunk_start_offset + chunk.chunk_length // 2
        data[middle : middle + 64] = bytes(64)
    file.write_bytes(bytes(data))
    reader = BagReader(tmp_path / "corrupt", recover=True)
    assert reader.topics()  # the summary is intact: only reading finds that no chunk is
    with pytest.warns(UserWarning, match="corrupt record"), pytest.raises(
            rosbag.BagUnreadable, match=rf"^nothing readable in {re.escape(str(file))}: it is damaged before its first"):
        list(reader)
    for bag in ("cut", "corrupt"):
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            assert rosbag.main(["repair", str(tmp_path / bag), "--out", str(tmp_path / f"fixed_{bag}")]) == 1
        assert capsys.readouterr().err.startswith(f"error: nothing readable in {tmp_path / bag}")
        assert not (tmp_path / f"fixed_{bag}").exists()
    # Into an existing empty folder (BagWriter takes one): the folder stays, empty.
    (tmp_path / "ready").mkdir()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        assert rosbag.main(["repair", str(tmp_path / "cut"), "--out", str(tmp_path / "ready")]) == 1
    assert capsys.readouterr().err.startswith(f"error: nothing readable in {tmp_path / 'cut'}")
    assert (tmp_path / "ready").is_dir() and not any((tmp_path / "ready").iterdir())


@pytest.mark.parametrize("content, reason", [
    ("rosbag2_bagfile_information: [unclosed\n  : - x: {", "not YAML: expected ',' or ']', but got ':' at line 2"),
    ("", "empty"),
    ("- a\n- b\n", "a YAML list, not rosbag2 metadata"),
    ("rosbag2_bagfile_information:\n  relative_file_paths: 7\n", "relative_file_paths is not a list of file names"),
    ("rosbag2_bagfile_information:\n  relative_file_paths: [unusable_0.mcap]\n  topics_with_message_count: [1]\n",
     "topics_with_message_count is not a list of topics with a name, type and message_count"),
    # replay sums the counts for its progress total: a count that is not a number would be a TypeError there
    ("rosbag2_bagfile_information:\n  relative_file_paths: [unusable_0.mcap]\n  topics_with_message_count:\n"
     "  - topic_metadata: {name: /ad_sim/instance, type: ad_msgs/msg/SimInstance}\n    message_count: two\n",
     "topics_with_message_count is not a list of topics with a name, type and message_count"),
    (None, None),  # valid, but naming a file that is not there
], ids=["not_yaml", "empty", "list", "bad_files", "bad_topics", "bad_count", "missing_file"])
def test_an_unusable_metadata_yaml_needs_recover_then_the_mcap_files_are_read(bag, tmp_path, capsys, content, reason):
    """A metadata.yaml that cannot be used does not block the intact .mcap beside it: a one-line error
    naming --recover; with it, or in `repair` (whose job this is), a one-line warning, then the .mcap
    files are read, as when metadata.yaml is missing."""
    source, written = bag
    path = tmp_path / "unusable"
    path.mkdir()
    shutil.copy(source / "two_0.mcap", path / "unusable_0.mcap")
    metadata = path / "metadata.yaml"
    if content is None:
        metadata.write_text((source / "metadata.yaml").read_text().replace("two_0.mcap", "gone_0.mcap"))
        problem = f"{metadata} names files that are missing: gone_0.mcap"
    else:
        metadata.write_text(content)
        problem = f"{metadata} is unreadable ({reason})"
    with pytest.raises(rosbag.BagDamaged) as refused:
        BagReader(path)
    assert str(refused.value) == f"{problem}; pass --recover to read the 1 .mcap file(s) beside it"
    assert "recover=True" in refused.value.__notes__[0]  # for Python callers, shown with a traceback
    with pytest.warns(UserWarning) as caught:
        reader = BagReader(path, recover=True)
    assert [str(w.message) for w in caught] == reader.problems == [f"{problem}; reading the 1 .mcap file(s) beside it"]
    assert [(t, s) for t, s, _ in reader] == [(t, s) for t, s, _ in written]
    with pytest.warns(UserWarning, match=re.escape(problem)):
        assert rosbag.main(["repair", str(path), "--out", str(tmp_path / "fixed")]) == 0
    assert capsys.readouterr().out == f"{tmp_path / 'fixed'}: {len(written)} messages written\n"
    assert len(list(BagReader(tmp_path / "fixed"))) == len(written)


def test_repair_to_an_out_that_cannot_be_created_is_one_line(bag, tmp_path, capsys):
    source, _ = bag
    (tmp_path / "file").write_text("keep")
    assert rosbag.main(["repair", str(source), "--out", str(tmp_path / "file" / "fixed")]) == 1
    assert capsys.readouterr().err == f"error: cannot create bag output {tmp_path / 'file' / 'fixed'}: Not a directory\n"
    assert (tmp_path / "file").read_text() == "keep"
    if Path("/proc/self").is_dir():  # a virtual file system where nothing can be created
        assert rosbag.main(["repair", str(source), "--out", "/proc/ad_sim_repair_test"]) == 1
        err = capsys.readouterr().err
        assert re.fullmatch(r"error: cannot create bag output /proc/ad_sim_repair_test: \S.*\n", err), err


def test_repair_takes_the_default_for_unusable_recorded_qos_and_keeps_every_message(bag, tmp_path, capsys):
    """offered_qos_profiles as the YAML string of rosbag2 before format 9: usable for the instance, not YAML for a
    mask topic, not a list of profiles for another. A warning line for each unusable one, whose topic gets the
    default profile, and the whole bag repaired (it was a YAML traceback, leaving a bag without topics at --out)."""
    source, written = bag
    path = tmp_path / "old"
    shutil.copytree(source, path)
    metadata_file = path / "metadata.yaml"
    metadata = yaml.safe_load(metadata_file.read_text())
    listed = {entry["topic_metadata"]["name"]: entry["topic_metadata"]
              for entry in metadata["rosbag2_bagfile_information"]["topics_with_message_count"]}
    instance = listed[messages.instance_topic()]
    instance["offered_qos_profiles"] = yaml.safe_dump(instance["offered_qos_profiles"])
    listed[messages.mask_topic(0)]["offered_qos_profiles"] = "- history: [unclosed"
    listed[messages.mask_topic(1)]["offered_qos_profiles"] = "garbage"
    metadata_file.write_text(yaml.safe_dump(metadata))
    with pytest.warns(UserWarning) as caught:
        assert rosbag.main(["repair", str(path), "--out", str(tmp_path / "fixed")]) == 0
    assert [str(w.message) for w in caught] == [
        f"{metadata_file}: unusable offered_qos_profiles for {messages.mask_topic(0)}: not YAML (expected ',' or ']', "
        "but got '<stream end>'); the repaired bag lists the default profile for it",
        f"{metadata_file}: unusable offered_qos_profiles for {messages.mask_topic(1)}: not a list of profiles "
        "('garbage'); the repaired bag lists the default profile for it"]
    assert capsys.readouterr().out == f"{tmp_path / 'fixed'}: {len(written)} messages written\n"
    assert [(t, s) for t, s, _ in BagReader(tmp_path / "fixed")] == [(t, s) for t, s, _ in written]
    repaired = yaml.safe_load((tmp_path / "fixed" / "metadata.yaml").read_text())["rosbag2_bagfile_information"]
    qos = {entry["topic_metadata"]["name"]: entry["topic_metadata"]["offered_qos_profiles"]
           for entry in repaired["topics_with_message_count"]}
    assert qos[messages.instance_topic()][0]["durability"] == "transient_local"  # as recorded
    assert qos[messages.mask_topic(0)] == qos[messages.mask_topic(1)] == [rosbag.qos_profile()]


def test_a_time_that_is_not_an_mcap_time_is_refused_and_the_bag_stays_whole(tmp_path):
    """A negative log or publish time: a BagError for that message, and the messages before and after it are in
    the closed bag (the MCAP writer kept the time in its statistics and failed on it again when closing)."""
    with BagWriter(tmp_path / "bag") as writer:
        writer.add_topic("/masks", messages.IMAGE_TYPE)
        writer.write("/masks", 5, b"before")
        with pytest.raises(BagError, match="^log time -1 ns or publish time -1 ns of a message on /masks is not an "
                                           r"MCAP time \(0 to 18446744073709551615 ns\)$"):
            writer.write("/masks", -1, b"negative")
        with pytest.raises(BagError, match="publish time -2 ns"):
            writer.write("/masks", 6, b"published before 1970", publish_time_ns=-2)
        writer.write("/masks", 7, b"after")
    assert [(m.log_time_ns, m.message) for m in BagReader(tmp_path / "bag", raw=True)] == [(5, b"before"), (7, b"after")]


def test_corrupt_chunk_names_file_and_offset(tmp_path):
    path = tmp_path / "corrupt"
    written = write_fabricated_bag(path, episodes=1, chunk_size=50_000)
    file = path / "corrupt_0.mcap"
    with open(file, "rb") as f:
        chunks = make_reader(f).get_summary().chunk_indexes
    target = chunks[len(chunks) // 2]
    (lost,) = [logged for offset, logged in _chunk_messages(file) if offset == target.chunk_start_offset]
    data = bytearray(file.read_bytes())
    middle = target.chunk_start_offset + target.chunk_length // 2
    data[middle : middle + 64] = bytes(64)
    file.write_bytes(bytes(data))
    with pytest.raises(BagError, match=rf"corrupt record \(opcode 0x06\) at byte {target.chunk_start_offset}.*--recover"):
        list(BagReader(path))
    with pytest.warns(UserWarning, match="corrupt"):
        recovered = list(BagReader(path, recover=True))
    # Only that chunk is lost: reading goes on at the record after it (the chunks after it are read).
    assert lost and len(recovered) == len(written) - len(lost)
    assert {(t, s) for t, s, _ in recovered} <= {(t, s) for t, s, _ in written}
    assert recovered[-1].log_time_ns == max(s for _, s, _ in written) > max(s for _, s in lost)


@pytest.mark.parametrize("points_at", ["far", "footer", "magic"])
def test_a_footer_pointing_outside_the_file_is_named_and_recoverable(tmp_path, points_at):
    """The footer's summary_start (bytes 9..17 of the footer record) overwritten: the error says where
    it points (it gave an empty reason), and --recover reads every message from the data section. At the
    footer itself (an empty summary) or inside the magic, it is outside the summary's place as well."""
    path = tmp_path / "bad_footer"
    written = write_fabricated_bag(path, episodes=1)
    file = path / "bad_footer_0.mcap"
    data = bytearray(file.read_bytes())
    footer = len(data) - 8 - 29  # magic 8, footer record: opcode 1 + length 8 + 3 x uint64/uint32
    start = {"far": 0xffffffffffff, "footer": footer, "magic": 7}[points_at]
    data[footer + 9 : footer + 17] = np.uint64(start).tobytes()
    file.write_bytes(bytes(data))
    with pytest.raises(BagError, match=rf"corrupt footer: its summary section starts at byte {start}, "
                                       rf"outside the file.s {len(data)} bytes before the footer.*--recover"):
        list(BagReader(path))
    with pytest.warns(UserWarning, match="corrupt footer.*reading the data section instead"):
        assert len(list(BagReader(path, recover=True))) == len(written)


def test_repair_makes_a_killed_writers_bag_whole_for_any_reader(tmp_path, capsys):
    """A copy of a bag whose writer never closed it (what kill -9 leaves: no summaries, metadata.yaml
    counting nothing): `repair` rewrites the flushed messages as a bag that rosbags, an independent
    reader, takes, with the true counts and each topic's offered QoS."""
    writer = BagWriter(tmp_path / "open")
    write_episodes(writer, [fabricated_episode(0), fabricated_episode(1)], 0)
    writer.flush()
    shutil.copytree(tmp_path / "open", tmp_path / "killed")  # before close: as a kill -9 leaves it
    writer.close()
    with pytest.raises(rosbag.BagDamaged, match="--recover"):
        list(BagReader(tmp_path / "killed"))
    with pytest.warns(UserWarning):
        recovered = [(m.topic, m.log_time_ns, m.message) for m in BagReader(tmp_path / "killed", raw=True, recover=True)]
    assert len(recovered) == 2 * 76

    with pytest.warns(UserWarning, match=f"no MCAP footer .*: recovered {len(recovered)} messages"):  # said, as lost
        assert rosbag.main(["repair", str(tmp_path / "killed"), "--out", str(tmp_path / "fixed")]) == 0
    assert f"{tmp_path / 'fixed'}: {len(recovered)} messages written" in capsys.readouterr().out
    assert [(m.topic, m.log_time_ns, m.message) for m in BagReader(tmp_path / "fixed", raw=True)] == recovered
    metadata = yaml.safe_load((tmp_path / "fixed" / "metadata.yaml").read_text())["rosbag2_bagfile_information"]
    assert metadata["message_count"] == len(recovered)
    qos = {t["topic_metadata"]["name"]: t["topic_metadata"]["offered_qos_profiles"][0]
           for t in metadata["topics_with_message_count"]}
    assert qos[messages.instance_topic()]["durability"] == "transient_local"  # latched, as recorded
    with AnyReader([tmp_path / "fixed"]) as reader:
        assert sum(1 for _ in reader.messages()) == len(recovered)
    assert rosbag.main(["repair", str(tmp_path / "killed"), "--out", str(tmp_path / "fixed")]) == 1
    assert "already exists" in capsys.readouterr().err


def test_unknown_schema_encoding_is_a_clear_error(tmp_path):
    path = tmp_path / "foreign.mcap"
    with open(path, "wb") as f:
        writer = Writer(f)
        writer.start(profile="", library="test")
        schema = writer.register_schema("Thing", "jsonschema", b"{}")
        channel = writer.register_channel("/thing", "json", schema)
        writer.add_message(channel, 1, b"{}", 1)
        writer.finish()
    with pytest.raises(BagError, match="only ros2msg/cdr"):
        list(BagReader(path))
    assert [m.message for m in BagReader(path, raw=True)] == [b"{}"]


def test_killed_writer_leaves_flushed_chunks_readable(tmp_path):
    """kill -9 of a process writing a bag: every flushed chunk reads back with recover=True."""
    path = tmp_path / "killed"
    script = textwrap.dedent(
        f"""
        import sys, time
        sys.path[:0] = [{str(Path(__file__).parent)!r}, {str(Path(__file__).parents[1] / "ros_ws" / "src" / "ad_sim")!r}]
        from sim_fixtures import fabricated_episode
        from ad_sim.generate import write_episodes
        from ad_sim.rosbag import BagWriter
        writer = BagWriter({str(path)!r})
        for index in range(1000):
            write_episodes(writer, [fabricated_episode(index % 3)], index)
            writer.flush()
            print(index, writer.message_count, flush=True)
        """
    )
    process = subprocess.Popen([sys.executable, "-c", script], stdout=subprocess.PIPE, text=True)
    flushed = 0
    for line in process.stdout:
        flushed = int(line.split()[1])
        if flushed >= 3 * 76:
            break
    os.kill(process.pid, signal.SIGKILL)
    process.wait()
    with pytest.raises(BagError, match="truncated"):
        list(BagReader(path))
    with pytest.warns(UserWarning):
        recovered = list(BagReader(path, recover=True))
    assert len(recovered) >= flushed
    instances = [m for m in recovered if m.topic == "/ad_sim/instance"]
    assert [m.message.episode_index for m in instances] == list(range(len(instances)))


# ------------------------------------------------------------------------------- damage found by fuzzing


def _chunk_messages(file: Path) -> list[tuple[int, list[tuple[int, int]]]]:
    """(chunk_start_offset, [(channel id, log time)] of its messages) of each chunk, from an intact file."""
    import io

    from mcap.data_stream import ReadDataStream
    from mcap.records import Chunk, Message
    from mcap.stream_reader import breakup_chunk

    data = file.read_bytes()
    with open(file, "rb") as f:
        indexes = make_reader(f).get_summary().chunk_indexes
    out = []
    for index in sorted(indexes, key=lambda c: c.chunk_start_offset):
        record = data[index.chunk_start_offset + 9 : index.chunk_start_offset + index.chunk_length]
        chunk = Chunk.read(ReadDataStream(io.BytesIO(record)))
        out.append((index.chunk_start_offset,
                    [(r.channel_id, r.log_time) for r in breakup_chunk(chunk) if isinstance(r, Message)]))
    return out


@pytest.mark.parametrize("damage", ["opcode_message_index", "opcode_data_end", "opcode_footer", "length_huge",
                                    "length_short"])
def test_a_chunk_whose_record_header_is_damaged_is_named_and_the_chunks_after_it_are_read(tmp_path, damage):
    """The opcode or length of a chunk record damaged (the summary, intact, lists the chunk there): it was skipped
    (another opcode), or everything after it was lost without a word (a data-end or footer opcode) or with a
    warning although the summary says where the next chunks are (a length past the end, or one too short). Now an
    error naming --recover, and recovering skips just that chunk."""
    path = tmp_path / "bag"
    written = write_fabricated_bag(path, episodes=1, chunk_size=50_000)
    file = path / "bag_0.mcap"
    chunks = _chunk_messages(file)
    offset, lost = chunks[len(chunks) // 2]
    assert lost and len(chunks) > 4
    data = bytearray(file.read_bytes())
    if damage.startswith("opcode"):
        data[offset] = {"opcode_message_index": 0x07, "opcode_data_end": 0x0F, "opcode_footer": 0x02}[damage]
    else:
        (length,) = np.frombuffer(bytes(data[offset + 1 : offset + 9]), "<u8")
        data[offset + 1 : offset + 9] = np.uint64(2**40 if damage == "length_huge" else length - 100).tobytes()
    file.write_bytes(bytes(data))
    with pytest.raises(rosbag.BagDamaged, match=rf"bag_0\.mcap.* at byte {offset}.*--recover"):
        list(BagReader(path))
    with pytest.warns(UserWarning, match=rf"bag_0\.mcap.* at byte {offset}"):
        recovered = [(m.topic, m.log_time_ns) for m in BagReader(path, recover=True)]
    assert len(recovered) == len(written) - len(lost)
    assert set(recovered) <= {(t, s) for t, s, _ in written}
    assert {s for _, s in recovered} >= {s for _, s, _ in written if s > max(t for _, t in lost)}  # the chunks after it


# Stamps of the chunks of _write_chunks' bags: the third chunk reaches back to 5 ns, before the second's.
CHUNK_STAMPS = [[0, 10, 20], [30, 40, 50], [5, 60, 70], [80, 90, 100]]


def _write_chunks(path: Path, chunks: list[list[int]]) -> list[int]:
    """A bag of one topic whose i-th chunk holds messages logged at chunks[i] (message k a 1x1 image of value k);
    returns the message values in log-time order (ties in file order)."""
    stamps = [stamp for chunk in chunks for stamp in chunk]
    with BagWriter(path, chunk_size=1 << 20) as writer:
        writer.add_topic("/a", "sensor_msgs/msg/Image")
        for chunk in chunks:
            for stamp in chunk:
                writer.write("/a", stamp, messages.mask_message(np.full((1, 1), writer.message_count, np.uint8), stamp, "f"))
            writer.flush()
    return sorted(range(len(stamps)), key=lambda k: stamps[k])


def _chunk_at(file: Path, stamp: int) -> int:
    """Offset of the chunk record holding the message logged at `stamp`."""
    (offset,) = [offset for offset, logged in _chunk_messages(file) if stamp in {t for _, t in logged}]
    return offset


@pytest.mark.parametrize("damaged", ["start", "end"])
def test_a_damaged_chunk_start_time_does_not_break_log_time_order(tmp_path, damaged):
    """A killed recorder's file (no summary) whose third chunk's header says its messages start at 60 ns (no CRC
    covers a chunk header; they start at 5 ns): messages were released up to 60 ns after the second chunk, and the
    one at 5 ns came after those at 10 to 50 ns, without a word. Now the chunks' start times are their messages' own,
    read ahead, and the damaged header is named; so is one whose end time (which reading does not use, but other
    readers' time queries do) ends before its last message, at 6 ns."""
    path = tmp_path / "bag"
    in_order = _write_chunks(path, CHUNK_STAMPS)
    file = path / "bag_0.mcap"
    offset = _chunk_at(file, 5)
    data = bytearray(file.read_bytes())
    if damaged == "start":
        data[offset + 9 : offset + 17] = np.uint64(60).tobytes()  # the header's message_start_time
    else:
        data[offset + 17 : offset + 25] = np.uint64(6).tobytes()  # the header's message_end_time
    footer = len(data) - 8 - 29
    data_end = int(np.frombuffer(bytes(data[footer + 9 : footer + 17]), "<u8")[0]) - 13  # summary_start - data end
    assert data[data_end] == rosbag.Opcode.DATA_END
    file.write_bytes(bytes(data[:data_end]))  # every chunk and its message indexes: what a kill after a flush leaves
    with pytest.warns(UserWarning) as caught:
        read = list(BagReader(path, recover=True))
    assert [m.log_time_ns for m in read] == sorted(t for chunk in CHUNK_STAMPS for t in chunk)
    assert [m.message.data[0] for m in read] == in_order
    gives = "60 to 70" if damaged == "start" else "5 to 6"
    assert [str(w.message) for w in caught if f"at byte {offset}" in str(w.message)] == [
        f"{file}: damaged chunk header at byte {offset}: it gives log times {gives} ns, its messages were logged "
        "from 5 to 70 ns; read in log-time order by their own times"]


def test_a_summary_whose_chunk_index_starts_too_late_is_named(tmp_path, monkeypatch):
    """A writer's error (the summary passes its CRC): the third chunk's index says its messages start at 60 ns, they
    start at 5 ns. Messages were released by it, as mcap's own reader does, and the one at 5 ns came after those at
    10 to 50 ns, without a word. Now an error naming --recover before that message, and recovering reads it late,
    with a warning; `repair` rewrites the bag, whose chunk indexes are then true, in log-time order."""
    from mcap._chunk_builder import ChunkBuilder

    add_message = ChunkBuilder.add_message

    def starting_late(self, message):
        add_message(self, message)
        if self.message_start_time == 5:
            self.message_start_time = 60

    monkeypatch.setattr(ChunkBuilder, "add_message", starting_late)
    path = tmp_path / "bag"
    in_order = _write_chunks(path, CHUNK_STAMPS)
    monkeypatch.undo()
    file = path / "bag_0.mcap"
    offset = _chunk_at(file, 5)
    read = []
    with pytest.raises(rosbag.BagDamaged, match=rf"bag_0\.mcap: the record at byte {offset} holds 1 message\(s\) "
                                                rf"logged from 5 ns, before messages read already \(up to 50 ns\): its "
                                                rf"chunk index says its messages start at 60 ns\..*--recover"):
        read.extend(m.log_time_ns for m in BagReader(path))
    assert read == [0, 10, 20, 30, 40, 50]
    with pytest.warns(UserWarning, match=rf"byte {offset} holds 1 message\(s\) logged from 5 ns.*; read late, out of "
                                         "log-time order$"):
        assert [m.log_time_ns for m in BagReader(path, recover=True)] == [0, 10, 20, 30, 40, 50, 5, 60, 70, 80, 90, 100]
    with pytest.warns(UserWarning, match="read late"):
        rosbag.repair(path, tmp_path / "fixed")
    assert [m.message.data[0] for m in BagReader(tmp_path / "fixed")] == in_order


def test_the_log_time_order_check_concerns_only_the_topics_read(tmp_path, monkeypatch):
    """A summary whose third chunk's index says its messages start at 60 ns, where a message on /b is logged at 5 ns
    (a writer's error, as above). Reading only /a, whose messages are all in order, was refused all the same (an error
    naming --recover about a message on /b that the caller had not asked for; recovering warned about it): the check
    looked at every topic's messages before the topic filter. Now it concerns the messages read: /a alone reads in
    order, without a word, and /b's messages are not decoded; reading /b (or every topic) is still refused."""
    from mcap._chunk_builder import ChunkBuilder

    add_message = ChunkBuilder.add_message

    def starting_late(self, message):
        add_message(self, message)
        if self.message_start_time == 5:
            self.message_start_time = 60

    chunks = [[("/a", 0), ("/b", 1), ("/a", 10), ("/a", 20)], [("/a", 30), ("/b", 31), ("/a", 40), ("/a", 50)],
              [("/b", 5), ("/a", 60), ("/a", 70)], [("/a", 80), ("/b", 81), ("/a", 90)]]
    monkeypatch.setattr(ChunkBuilder, "add_message", starting_late)
    path = tmp_path / "bag"
    with BagWriter(path, chunk_size=1 << 20) as writer:
        writer.add_topic("/a", "sensor_msgs/msg/Image")
        writer.add_topic("/b", "sensor_msgs/msg/Image")
        for chunk in chunks:
            for topic, stamp in chunk:
                writer.write(topic, stamp, messages.mask_message(np.full((1, 1), stamp, np.uint8), stamp, "f"))
            writer.flush()
    monkeypatch.undo()
    offset = _chunk_at(path / "bag_0.mcap", 5)
    decoded = []
    decode = BagReader._decode
    monkeypatch.setattr(BagReader, "_decode", lambda self, scan, channel, data: decoded.append(channel.topic)
                        or decode(self, scan, channel, data))
    a = sorted(stamp for chunk in chunks for topic, stamp in chunk if topic == "/a")
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # not even a warning about /b
        assert [(m.topic, m.log_time_ns) for m in BagReader(path, topics=["/a"])] == [("/a", s) for s in a]
        assert [m.message.data[0] for m in BagReader(path, topics=["/a"])] == a
        assert [m.log_time_ns for m in BagReader(path, topics=["/a"], recover=True)] == a
    assert set(decoded) == {"/a"}
    for topics, up_to in ((["/b"], 31), (None, 50)):
        with pytest.raises(rosbag.BagDamaged, match=rf"the record at byte {offset} holds 1 message\(s\) logged from "
                                                    rf"5 ns, before messages read already \(up to {up_to} ns\).*--recover"):
            list(BagReader(path, topics=topics, raw=True))
    with pytest.warns(UserWarning, match=rf"byte {offset} holds 1 message\(s\) logged from 5 ns.*read late"):
        assert [m.log_time_ns for m in BagReader(path, topics=["/b"], recover=True)] == [1, 31, 5, 81]


def test_a_summary_that_fails_its_crc_is_not_trusted(tmp_path):
    """A byte of the summary section damaged (here a letter of a topic name in a Channel record): the footer's
    summary CRC says so, but topics() reported the damaged name (and `repair` failed on it, leaving a bag behind).
    Now an error naming --recover, and recovering reads the topics from the data section."""
    path = tmp_path / "bag"
    write_fabricated_bag(path, episodes=1, chunk_size=50_000)
    file = path / "bag_0.mcap"
    data = bytearray(file.read_bytes())
    footer = len(data) - 8 - 29
    summary_start = int(np.frombuffer(bytes(data[footer + 9 : footer + 17]), "<u8")[0])
    at = data.index(b"/ad_sim/instance", summary_start)
    data[at + 1] ^= 0x01  # "/`d_sim/instance"
    file.write_bytes(bytes(data))
    for read in (BagReader.topics, list):
        with pytest.raises(rosbag.BagDamaged, match=rf"bag_0\.mcap: corrupt summary section .*CRC.*--recover"):
            read(BagReader(path))
    with pytest.warns(UserWarning, match="corrupt summary section"):
        topics = BagReader(path, recover=True).topics()
    assert set(topics) == set(messages.topic_types(1))


@pytest.mark.parametrize("listed", ["twice", "dotdot"])
def test_a_file_that_metadata_yaml_names_twice_is_not_read_twice(bag, tmp_path, listed):
    """relative_file_paths naming one file twice, or by another path to it ("../copy/copy_0.mcap"): every message
    was read twice (the second time as a file "not named in metadata.yaml"). Now a file named twice makes
    metadata.yaml unusable (an error naming --recover; recovering reads each file once), and a file named by
    another path to it is that file."""
    source, written = bag
    path = tmp_path / "copy"
    path.mkdir()
    shutil.copy(source / "two_0.mcap", path / "copy_0.mcap")
    metadata = yaml.safe_load((source / "metadata.yaml").read_text())
    names = ["copy_0.mcap", "copy_0.mcap"] if listed == "twice" else ["../copy/copy_0.mcap"]
    metadata["rosbag2_bagfile_information"]["relative_file_paths"] = names
    (path / "metadata.yaml").write_text(yaml.safe_dump(metadata))
    if listed == "twice":
        with pytest.raises(rosbag.BagDamaged, match=r"metadata\.yaml names copy_0\.mcap more than once.*--recover"):
            BagReader(path)
        with pytest.warns(UserWarning, match="more than once"):
            assert len(list(BagReader(path, raw=True, recover=True))) == len(written)
    else:
        with warnings.catch_warnings():
            warnings.simplefilter("error")
            assert len(list(BagReader(path, raw=True))) == len(written)


def test_a_repair_that_fails_leaves_nothing_behind(bag, tmp_path, capsys):
    """A bag that `repair` cannot read (here a file in it that is not MCAP, an error even when recovering): the
    error line, and no bag at --out; it left a complete-looking bag with the messages read before the failure."""
    source, _ = bag
    path = tmp_path / "foreign"
    shutil.copytree(source, path)
    (path / "two_1.mcap").write_bytes(b"not an mcap file at all")
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        assert rosbag.main(["repair", str(path), "--out", str(tmp_path / "fixed")]) == 1
    assert capsys.readouterr().err.startswith(f"error: {path / 'two_1.mcap'} is not an MCAP file")
    assert not (tmp_path / "fixed").exists()


# ------------------------------------------------------------------------------- a disk that fills up


class _FillingFile:
    """A bag file whose disk fills up after `room` more bytes (the write that crosses it is partial, as the OS
    writes what fits, the next raises ENOSPC); room None: there is space again."""

    def __init__(self, file, room: int | None = None):
        self.file, self.room = file, room

    def write(self, data) -> int:
        if self.room is not None:
            if self.room == 0:
                raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
            data = data[: self.room]
            self.room -= len(data)
        return self.file.write(data)

    def __getattr__(self, name):
        return getattr(self.file, name)


def test_a_full_disk_stops_the_writer_and_keeps_every_chunk_written_before(tmp_path):
    """The disk fills up in the middle of a chunk, then has space again. The writer went on after the OS error:
    its next chunk followed the half-written one, and reading (even with --recover) lost every message after the
    error point; the error named no file; metadata.yaml and the writer counted the messages of the lost chunk. Now
    the half-written record is cut off, writing stops with an error naming the file and what to do, and the file
    reads back with --recover up to its last complete chunk, as a killed writer's does; `lost` counts the rest."""
    path = tmp_path / "full"
    episodes = [fabricated_episode(seed) for seed in range(4)]
    writer = BagWriter(path, chunk_size=100_000)
    items = [item for index, episode in enumerate(episodes) for item in messages.episode_messages(episode, index)]
    for topic, type_name in messages.topic_types(1).items():
        writer.add_topic(topic, type_name)
    flushed_at = len(items) // 2
    for topic, stamp, message in items[:flushed_at]:
        writer.write(topic, stamp, message)
    writer.flush()
    stream = writer._stream
    stream._file = _FillingFile(stream._file, room=1000)  # the next chunk is written in part
    written = flushed_at
    with pytest.raises(OSError, match=rf"cannot write {re.escape(str(path / 'full_0.mcap'))}: No space left on "
                                      r"device\. Writing stopped.*--recover.*ad_sim\.rosbag repair") as failure:
        for topic, stamp, message in items[flushed_at:]:
            writer.write(topic, stamp, message)
            written += 1
    assert isinstance(failure.value, BagError)
    stream._file.room = None  # space again: nothing more is written after the half chunk
    for topic, stamp, message in items[-3:]:
        with pytest.raises(BagError, match="Writing stopped"):
            writer.write(topic, stamp, message)
    writer.close()  # the error was raised already
    with pytest.warns(UserWarning) as caught:
        recovered = [(m.topic, m.log_time_ns) for m in BagReader(path, recover=True, raw=True)]
    assert all("corrupt" not in str(w.message) for w in caught), [str(w.message) for w in caught]
    assert sorted(recovered) == sorted((t, s) for t, s, _ in items[:flushed_at])
    assert sum(writer.lost.values()) == written - flushed_at > 0
    metadata = yaml.safe_load((path / "metadata.yaml").read_text())["rosbag2_bagfile_information"]
    assert metadata["message_count"] == writer.message_count == len(recovered)
    assert not list(path.glob("*.tmp"))


def test_a_disk_full_at_the_start_is_an_oserror_naming_the_file(tmp_path, monkeypatch):
    """No room for the first file's header: the OSError (what `record` and `generate` report, as for a folder that
    cannot be made) said "[Errno 28] No space left on device" and named no file."""

    def full(self, data):
        raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))

    monkeypatch.setattr(rosbag._UnbufferedFile, "write", full)
    with pytest.raises(OSError, match=re.escape(f"No space left on device: '{tmp_path / 'bag' / 'bag_0.mcap'}'")):
        BagWriter(tmp_path / "bag")


def test_a_repair_onto_a_full_disk_is_one_line_and_leaves_nothing(bag, tmp_path, capsys, monkeypatch):
    """The disk holding --out fills up while `repair` writes: a traceback ending in "OSError: [Errno 28] No space
    left on device" (main() reported BagErrors only), and the half-made bag left at --out."""
    source, _ = bag
    write = rosbag._UnbufferedFile.write

    def full_for_chunks(self, data):  # room for a file's header, not for its chunks
        if len(data) > 1000:
            raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
        return write(self, data)

    monkeypatch.setattr(rosbag._UnbufferedFile, "write", full_for_chunks)
    assert rosbag.main(["repair", str(source), "--out", str(tmp_path / "fixed")]) == 1
    assert capsys.readouterr().err == (f"error: cannot write the repaired bag {tmp_path / 'fixed'}: No space left on "
                                       "device; nothing is left there. Free space on that file system, or pass "
                                       "another --out\n")
    assert not (tmp_path / "fixed").exists()


def test_a_split_that_cannot_open_the_next_file_loses_no_message_it_said_it_wrote(tmp_path, monkeypatch):
    """The write that reaches max_bag_size closes its file, then the next file cannot be made (a full disk). The
    write raised, though its message is in the closed, complete file (a recorder counted it lost). Now that write
    returns, the next one raises naming the file that could not be made, and every message whose write returned is
    read back; with no next write, close() raises it."""
    opened = rosbag._UnbufferedFile.__init__

    def no_second_file(self, path):
        if path.name.endswith("_1.mcap"):
            raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC), str(path))
        opened(self, path)

    data = bytes(4) + np.random.default_rng(0).random(2500, dtype=np.float32).tobytes()
    options = {"max_bag_size": rosbag.MIN_SPLIT_SIZE, "chunk_size": 20_000}
    with BagWriter(tmp_path / "dry", **options) as writer:  # how many messages fill the first file
        writer.add_topic("/p", "sensor_msgs/msg/PointCloud2")
        while not (tmp_path / "dry" / "dry_1.mcap").exists():
            writer.write("/p", writer.message_count, data)
        fill = writer.message_count
    monkeypatch.setattr(rosbag._UnbufferedFile, "__init__", no_second_file)
    for then in ("write", "close"):
        path = tmp_path / then
        writer = BagWriter(path, **options)
        writer.add_topic("/p", "sensor_msgs/msg/PointCloud2")
        returned = 0
        for _ in range(fill):
            writer.write("/p", returned, data)
            returned += 1
        with pytest.raises(BagError, match=re.escape(f"cannot write {path / f'{then}_1.mcap'}: No space left")):
            if then == "write":
                writer.write("/p", returned, data)
            writer.close()
        writer.close()
        assert len(list(BagReader(path, raw=True))) == returned == writer.message_count


def _failing_on(opcode: int):
    """_UnbufferedFile.write raising ENOSPC for the record group that starts with `opcode`, once armed."""
    write = rosbag._UnbufferedFile.write
    armed = []

    def failing(self, data):
        if armed and bytes(data[:1]) == bytes([opcode]):
            raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
        return write(self, data)

    return failing, armed


def test_a_failure_after_the_last_chunk_was_written_loses_none_of_its_messages(tmp_path, monkeypatch):
    """close() writes the chunk in progress, then the data end and the summary. When the disk fills up after the
    chunk (at the data end), the chunk's messages are in the file, complete, yet `lost` counted them and the counts
    (metadata.yaml, a recorder's `written`) left them out: the bag held more than it said."""
    failing, armed = _failing_on(rosbag.Opcode.DATA_END)
    monkeypatch.setattr(rosbag._UnbufferedFile, "write", failing)
    data = bytes(4) + bytes(400)
    writer = BagWriter(tmp_path / "bag", chunk_size=1_000_000)  # every message in the chunk close() writes
    writer.add_topic("/p", "sensor_msgs/msg/PointCloud2")
    for stamp in range(20):
        writer.write("/p", stamp, data)
    armed.append(1)
    with pytest.raises(rosbag.BagWriteError, match="Writing stopped"):
        writer.close()
    with pytest.warns(UserWarning, match="truncated"):
        recovered = list(BagReader(tmp_path / "bag", recover=True, raw=True))
    assert len(recovered) == 20
    assert sum(writer.lost.values()) == 0 and writer.message_count == 20
    metadata = yaml.safe_load((tmp_path / "bag" / "metadata.yaml").read_text())["rosbag2_bagfile_information"]
    assert metadata["message_count"] == 20


def test_a_chunk_written_by_a_topic_added_later_is_not_counted_lost(tmp_path, monkeypatch):
    """Adding a topic registers its channel in the chunk in progress, which can fill it and write it: the messages
    in it are in the file, but `lost` still counted them when the next write failed."""
    failing, armed = _failing_on(rosbag.Opcode.CHUNK)
    monkeypatch.setattr(rosbag._UnbufferedFile, "write", failing)
    data = bytes(4) + bytes(400)
    writer = BagWriter(tmp_path / "bag", chunk_size=5000, compression="none")
    writer.add_topic("/p", "sensor_msgs/msg/PointCloud2")
    file = tmp_path / "bag" / "bag_0.mcap"
    while file.stat().st_size < 100:  # up to the first chunk (with the schema and channel): the header only before
        writer.write("/p", writer.message_count, data)
    # fill the next chunk up to just under its size, then add a topic: its channel record writes the chunk
    size, count = file.stat().st_size, writer.message_count
    for _ in range(11):  # 11 messages of ~430 bytes: under 5000
        writer.write("/p", writer.message_count, data)
    assert file.stat().st_size == size
    writer.add_topic("/q", "sensor_msgs/msg/PointCloud2")  # its channel pushes the chunk over its size
    assert file.stat().st_size > size, "the channel did not write the chunk"
    armed.append(1)
    writer.write("/q", writer.message_count, data)
    with pytest.raises(rosbag.BagWriteError):
        writer.flush()
    writer.close()
    with pytest.warns(UserWarning, match="truncated"):
        recovered = list(BagReader(tmp_path / "bag", recover=True, raw=True))
    assert len(recovered) == count + 11 == writer.message_count
    assert writer.lost == {"/q": 1}


def test_distinct_episodes_keeps_the_last_of_one_episode_and_passes_over_others_at_one_stamp():
    """At one stamp, ground truth of one episode (id and seed) received twice is that episode, with the frames
    (which all went to the last); episodes of one id but another seed there cannot be told apart."""
    from types import SimpleNamespace as NS

    from ad_sim.rosbag import BagEpisode, distinct_episodes

    a1 = BagEpisode(NS(episode_id="a", seed=1), 0)
    a2 = BagEpisode(NS(episode_id="a", seed=1), 0, {"/m": [(0, "f")]})
    b1, b2 = BagEpisode(NS(episode_id="b", seed=2), 5), BagEpisode(NS(episode_id="b", seed=3), 5)
    groups = []
    assert list(distinct_episodes([a1, a2, b1, b2], lambda group, reason: groups.append(group))) == [a2]
    assert groups == [[b1, b2]]


# ------------------------------------------------------------------------------- found by mutation testing


def test_a_bag_folder_without_metadata_yaml_is_read_in_its_files_natural_order(tmp_path):
    """A killed recorder's folder, or a copy that left metadata.yaml out: its .mcap files are read with a warning
    saying so, in their natural order (split_2 before split_10, as rosbag2 numbers them). Untested so far: messages
    logged at one time are read in file order, so names sorted as text (split_10 before split_2) would put those of
    the eleventh file and later before the third's; and the warning is all that tells a user the files were found
    without their metadata (a truncated or incomplete bag)."""
    rng = np.random.default_rng(0)
    payloads = [bytes(4) + rng.bytes(3000) for _ in range(300)]  # incompressible: a dozen files or more
    path = tmp_path / "split"
    with BagWriter(path, max_bag_size=rosbag.MIN_SPLIT_SIZE) as writer:
        writer.add_topic("/p", "sensor_msgs/msg/PointCloud2")
        for payload in payloads:
            writer.write("/p", 7, payload)  # one log time: the order read is the file order
    files = len(list(path.glob("*.mcap")))
    assert files >= 12, files
    assert [m.message for m in BagReader(path, raw=True)] == payloads  # as metadata.yaml lists them
    (path / "metadata.yaml").unlink()
    with pytest.warns(UserWarning) as caught:
        reader = BagReader(path, raw=True)
    assert [str(w.message) for w in caught] == reader.problems == [
        f"bag {path} has no metadata.yaml (was the writer killed?); reading the {files} .mcap file(s) found"]
    assert [m.message for m in reader] == payloads


def test_an_unusable_metadata_yaml_with_no_mcap_beside_it_is_an_error_that_recover_cannot_help(tmp_path):
    """A folder holding only a broken metadata.yaml (a copy that lost its .mcap files): --recover reads the .mcap
    files beside such a file, and there are none, so the error must not advise it ("pass --recover to read the 0
    .mcap file(s)"), with or without it."""
    path = tmp_path / "only_metadata"
    path.mkdir()
    (path / "metadata.yaml").write_text("- a\n- b\n")
    for recover in (False, True):
        with pytest.raises(BagError) as refused:
            BagReader(path, recover=recover)
        assert not isinstance(refused.value, rosbag.BagDamaged)
        assert str(refused.value) == (f"{path / 'metadata.yaml'} is unreadable (a YAML list, not rosbag2 metadata), "
                                      "and no .mcap file lies beside it")


def test_an_empty_topic_list_reads_no_message(tmp_path):
    """topics=[] asks for no topic (training/data.py passes the topics of a bag that it wants, which can be none):
    nothing is read or decoded. Untested so far: an empty list taken as no filter would decode every topic, here
    one that does not decode, which stops the reading of a bag the caller wanted nothing from."""
    path = tmp_path / "bag"
    with BagWriter(path) as writer:
        writer.add_topic("/masks", messages.IMAGE_TYPE)
        writer.write("/masks", 5, b"\x00\x01\x00\x00 not an image")
    with pytest.raises(rosbag.BagDamaged, match="does not decode"):
        list(BagReader(path))
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert list(BagReader(path, topics=[])) == []


def _write_other_mcap(path: Path, stamps: list[int], reorder_chunk_indexes: bool = False,
                      **writer_options) -> list[int]:
    """An MCAP file written by mcap's own Writer with `writer_options` (parts that MCAP makes optional and other
    writers leave out): one topic /a of 1x1 images, message k stamped stamps[k] with value k, a few per chunk;
    `reorder_chunk_indexes`: the summary lists the chunks last first. Returns the values in log-time order."""
    from mcap_ros2._dynamic import serialize_dynamic

    schema = rosbag.load_schema(messages.IMAGE_TYPE)
    encode = serialize_dynamic(schema.name, schema.definition)[schema.name]
    with open(path, "wb") as f:
        writer = Writer(f, chunk_size=200, **writer_options)
        writer.start(profile="ros2", library="another writer")
        channel = writer.register_channel("/a", "cdr", writer.register_schema(schema.name, "ros2msg",
                                                                              schema.definition.encode()))
        for k, stamp in enumerate(stamps):
            writer.add_message(channel, stamp, encode(messages.mask_message(np.full((1, 1), k, np.uint8), stamp, "f")),
                               stamp)
        if reorder_chunk_indexes:
            writer._Writer__chunk_indices.reverse()  # in the summary it writes at finish()
        writer.finish()
    return sorted(range(len(stamps)), key=lambda k: stamps[k])


OTHER_STAMPS = [0, 10, 5, 20, 30, 25, 40, 35, 50, 45, 60, 70]


@pytest.mark.parametrize("written_with", ["no_crcs", "no_summary", "no_message_indexes", "chunk_indexes_reordered"])
def test_mcap_files_of_other_writers_without_optional_parts_read_as_they_are(tmp_path, written_with):
    """MCAP makes CRCs, the summary section and message indexes optional, and does not order the chunk indexes; other
    writers (and rosbag2 settings) leave them out. A summary CRC of 0 means none, not a damaged summary; a footer with
    summary_start 0 means no summary, not a damaged footer; chunks back to back (no message indexes between them) do
    not overlap; chunk indexes in another order than their chunks are not damage. Untested so far (every bag of the
    tests came from BagWriter): taken for damage, each would be refused, naming --recover, though nothing is."""
    from mcap.writer import IndexType

    options = {
        "no_crcs": {"enable_crcs": False},
        "no_summary": {"repeat_schemas": False, "repeat_channels": False, "use_statistics": False,
                       "index_types": IndexType.NONE, "use_summary_offsets": False},
        "no_message_indexes": {"index_types": IndexType.CHUNK},
        "chunk_indexes_reordered": {"reorder_chunk_indexes": True},
    }[written_with]
    file = tmp_path / "other.mcap"
    in_order = _write_other_mcap(file, OTHER_STAMPS, **options)
    data = file.read_bytes()
    footer = len(data) - 8 - 29
    summary_start = int.from_bytes(data[footer + 9 : footer + 17], "little")
    summary_crc = data[footer + 25 : footer + 29]
    assert (summary_start == 0) == (written_with == "no_summary")
    assert (summary_crc == bytes(4)) == (written_with == "no_crcs")
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        reader = BagReader(file)
        assert reader.topics() == {"/a": messages.IMAGE_TYPE}
        read = list(reader)
    assert [m.log_time_ns for m in read] == sorted(OTHER_STAMPS)
    assert [m.message.data[0] for m in read] == in_order
    assert reader.problems == []


def _chunks_in_file_order(file: Path) -> list:
    """The chunk indexes of an MCAP file's summary, in the order of the chunks in the file."""
    with open(file, "rb") as f:
        return sorted(make_reader(f).get_summary().chunk_indexes, key=lambda c: c.chunk_start_offset)


def test_a_summary_without_crc_whose_chunk_index_points_past_the_data_section_is_not_used(tmp_path):
    """Without a CRC (a writer that computes none), a damaged chunk index is found by where it points: one past the
    data section (here into the summary) makes the summary unusable, said as such, and recovering reads the data
    section. Untested so far: used, it would blame the data end as a corrupt record before a chunk that is not
    there, sending the user to look for damage where there is none."""
    from mcap.writer import IndexType

    file = tmp_path / "other.mcap"
    in_order = _write_other_mcap(file, OTHER_STAMPS, enable_crcs=False, index_types=IndexType.CHUNK)
    last = _chunks_in_file_order(file)[-1]
    data = bytearray(file.read_bytes())
    footer = len(data) - 8 - 29
    summary_start = int.from_bytes(data[footer + 9 : footer + 17], "little")
    fields = np.array([last.message_start_time, last.message_end_time, last.chunk_start_offset], "<u8").tobytes()
    at = data.index(fields, summary_start) + 16  # the chunk index's chunk_start_offset
    data[at : at + 8] = np.uint64(summary_start).tobytes()
    file.write_bytes(bytes(data))
    with pytest.raises(rosbag.BagDamaged, match=rf"other\.mcap: corrupt summary section at byte {summary_start}: a "
                                                r"chunk index points past the data section .*--recover"):
        list(BagReader(file))
    with pytest.warns(UserWarning, match="corrupt summary section") as caught:
        read = list(BagReader(file, recover=True))
    assert [m.message.data[0] for m in read] == in_order
    assert all("corrupt record" not in str(w.message) for w in caught), [str(w.message) for w in caught]


@pytest.mark.parametrize("opcode", [0x0F, 0x02], ids=["data_end", "footer"])
def test_a_data_end_or_footer_opcode_between_chunks_is_named_and_the_chunks_after_it_are_read(tmp_path, opcode):
    """The opcode of a message index record (between two chunks) damaged into a data end or a footer. The summary
    lists chunks after it, so it is damage: an error naming --recover, and recovering skips to the next chunk,
    losing no message (only that chunk's message indexes). Untested so far (the chunk records' own opcodes were):
    taken for the end of the data section, every chunk after it would be lost without a word, even without
    --recover."""
    path = tmp_path / "bag"
    written = write_fabricated_bag(path, episodes=1, chunk_size=50_000)
    file = path / "bag_0.mcap"
    chunks = _chunks_in_file_order(file)
    assert len(chunks) > 4
    damaged = chunks[1].chunk_start_offset + chunks[1].chunk_length  # the message indexes after the second chunk
    data = bytearray(file.read_bytes())
    assert data[damaged] == rosbag.Opcode.MESSAGE_INDEX
    data[damaged] = opcode
    file.write_bytes(bytes(data))
    with pytest.raises(rosbag.BagDamaged, match=rf"bag_0\.mcap: corrupt record at byte {damaged} \(opcode "
                                                rf"0x{opcode:02x}.*the summary lists a chunk at byte "
                                                rf"{chunks[2].chunk_start_offset}.*--recover"):
        list(BagReader(path))
    with pytest.warns(UserWarning, match=rf"at byte {damaged} .*skipped to that chunk"):
        recovered = [(m.topic, m.log_time_ns) for m in BagReader(path, recover=True, raw=True)]
    assert recovered == [(t, s) for t, s, _ in written]


def test_a_writer_killed_between_a_chunk_and_its_message_indexes_loses_no_message(tmp_path):
    """The writer writes a chunk, then its message indexes: killed between the two, its file ends with the whole
    chunk. That chunk is complete and read back, and the warning says nothing is lost. Untested so far (the killed
    writers' files of the tests end with message indexes): a record that ends at the end of the file taken as cut
    would lose the last chunk's messages."""
    path = tmp_path / "killed"
    written = write_fabricated_bag(path, episodes=1, chunk_size=50_000)
    file = path / "killed_0.mcap"
    last = _chunks_in_file_order(file)[-1]
    cut = last.chunk_start_offset + last.chunk_length
    file.write_bytes(file.read_bytes()[:cut])
    with pytest.warns(UserWarning) as caught:
        recovered = [(m.topic, m.log_time_ns) for m in BagReader(path, recover=True, raw=True)]
    assert recovered == [(t, s) for t, s, _ in written]
    assert [str(w.message) for w in caught] == [
        f"{file} is truncated: no MCAP footer ({cut} bytes; was the writer killed?): recovered {len(written)} messages"]


def test_a_message_on_a_channel_the_file_does_not_define_is_named_and_skipped_with_recover(tmp_path):
    """A message whose channel id names no channel record (a writer's error, or a damaged id): it cannot be decoded
    or given a topic, so an error naming --recover, and recovering skips just it, saying so. Untested so far: a
    message dropped without a word is one a user never learns is missing."""
    file = tmp_path / "orphan.mcap"
    schema = rosbag.load_schema(messages.IMAGE_TYPE)
    with open(file, "wb") as f:
        writer = Writer(f)
        writer.start(profile="ros2", library="test")
        channel = writer.register_channel("/a", "cdr", writer.register_schema(schema.name, "ros2msg",
                                                                              schema.definition.encode()))
        for stamp in (1, 2, 3):
            writer.add_message(channel if stamp != 2 else channel + 7, stamp, b"\x00\x01\x00\x00", stamp)
        writer.finish()
    with pytest.raises(rosbag.BagDamaged, match=rf"orphan\.mcap: message at byte \d+ names unknown channel "
                                                rf"{channel + 7}.*--recover"):
        list(BagReader(file, raw=True))
    with pytest.warns(UserWarning, match=rf"names unknown channel {channel + 7}; skipped it"):
        assert [m.log_time_ns for m in BagReader(file, raw=True, recover=True)] == [1, 3]


def test_a_cut_record_in_a_file_without_a_summary_is_said_to_lose_what_follows(tmp_path):
    """A file with a footer but no summary (another writer's, which MCAP allows) whose chunk length is damaged to
    run past the end of the file: what follows it cannot be found without a summary. An error naming --recover, and
    recovering reads the chunks before it with a warning of what was lost. Untested so far (the recovered-and-lost
    warning was tested for files without a footer only): without it, the rest of the file is lost without a word."""
    from mcap.writer import IndexType

    file = tmp_path / "other.mcap"
    _write_other_mcap(file, OTHER_STAMPS, repeat_schemas=False, repeat_channels=False, use_statistics=False,
                      index_types=IndexType.NONE, use_summary_offsets=False)
    data = bytearray(file.read_bytes())
    offsets, pos = [], 8  # the chunk records, walked from the first record after the magic
    while data[pos] != rosbag.Opcode.DATA_END:
        if data[pos] == rosbag.Opcode.CHUNK:
            offsets.append(pos)
        pos += 9 + int.from_bytes(data[pos + 1 : pos + 9], "little")
    assert len(offsets) > 3
    damaged = offsets[2]
    data[damaged + 1 : damaged + 9] = np.uint64(len(data)).tobytes()
    file.write_bytes(bytes(data))
    with pytest.raises(rosbag.BagDamaged, match=rf"other\.mcap is truncated or corrupt at byte {damaged}: .*--recover"):
        list(BagReader(file))
    with pytest.warns(UserWarning) as caught:
        read = [m.log_time_ns for m in BagReader(file, recover=True)]
    before = len(read)
    assert 0 < before < len(OTHER_STAMPS)
    assert [str(w.message) for w in caught] == [
        f"{file} is truncated or corrupt: recovered {before} messages; the last {len(data) - damaged} bytes (an "
        f"incomplete record at byte {damaged}) are lost"]


def test_a_parameter_sweep_recorded_into_one_bag_is_not_taken_for_one_episode(tmp_path):
    """The simulator node's single-instance mode names each run's episode by its shape and family with the seed
    asked for, and stamps it from 0 s: a stiffness sweep recorded into one bag is episodes of one id and seed at one
    stamp, whose frames group_episodes gives all to the last. distinct_episodes took them for one episode recorded
    twice and kept the last: the frames of every run (three at each stamp) under the last run's ground truth, and
    nothing said so (evaluate and training read that as one episode). They are distinct simulations (as training's
    episode keys and evaluate's simulation_key have it): passed to `collided`, as episodes of several runs at one
    stamp are. One run recorded twice (the same ground truth) is still kept once, with its frames."""
    from ad_sim.rosbag import distinct_episodes

    runs = []
    for modulus in (2e4, 2e5, 2e6):
        episode = fabricated_episode(0, material="jelly")
        episode.instance.parameters = {**episode.instance.parameters, "youngs_modulus": modulus}
        runs.append(episode)
    with BagWriter(tmp_path / "sweep") as writer:
        for episode in runs:
            write_episodes(writer, [episode], 0)  # each run stamped from 0 s
    with BagWriter(tmp_path / "twice") as writer:
        for _ in range(2):
            write_episodes(writer, runs[:1], 0)

    def read(bag):
        collided = []
        kept = list(distinct_episodes(group_episodes(BagReader(bag)), lambda group, reason: collided.append(group)))
        return kept, collided

    kept, collided = read(tmp_path / "sweep")
    assert kept == [] and len(collided) == 1
    assert [ep.instance.parameters[list(ep.instance.parameter_names).index("youngs_modulus")] for ep in collided[0]] \
        == [2e4, 2e5, 2e6]
    kept, collided = read(tmp_path / "twice")
    assert collided == [] and len(kept) == 1
    assert kept[0].instance.parameters[0] == 2e4 and len(kept[0].messages[messages.mask_topic(0)]) == 2 * 25
