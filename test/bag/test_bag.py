"""csam_ros.bag without DDS: bags written by BagWriter read back by read_bag, by rosbags
(rosbag2 Reader + typestore) and by mcap + mcap_ros2, field by field; killed and damaged
bags; rosbag2 metadata and QoS conventions; clear errors."""

from __future__ import annotations

import json
import os
import sys
from pathlib import Path
from typing import Any

import pytest
import yaml

from csam_ros.bag import (
    BagError,
    BagWriter,
    MessageTypes,
    inspect_bag,
    parse_qos_profiles,
    publisher_qos,
    qos_to_dict,
    read_bag,
    read_bag_messages,
    subscription_qos,
)

SECOND = 1_000_000_000


def _transient_local(depth: int = 1) -> Any:
    from rclpy.qos import DurabilityPolicy, QoSProfile

    return QoSProfile(depth=depth, durability=DurabilityPolicy.TRANSIENT_LOCAL)


@pytest.fixture
def sample_bag(tmp_path: Path, sample_messages: dict[str, Any]) -> tuple[Path, list[tuple]]:
    """A bag with two messages of every custom type (one topic per type; the LocalMap topic
    transient local), written with stamps out of order, first as serialized bytes, then as
    the rclpy message. Returns it and what was written: (stamp, topic, msgtype, message,
    bytes or None)."""
    from rclpy.serialization import serialize_message

    path = tmp_path / "sample"
    written = []
    with BagWriter(path) as bag:
        for i, (msgtype, message) in enumerate(sample_messages.items()):
            topic = f"/sample/{msgtype.split('/')[-1].lower()}"
            bag.add_topic(topic, msgtype, _transient_local(3) if "LocalMap" in msgtype else None)
            data = serialize_message(message)
            bag.write(topic, (100 - i) * SECOND, data)
            bag.write(topic, (200 + i) * SECOND + 7, message)
            written.append(((100 - i) * SECOND, topic, msgtype, message, data))
            written.append(((200 + i) * SECOND + 7, topic, msgtype, message, None))
    written.sort(key=lambda item: item[0])
    return path, written


def test_read_bag_returns_every_message_in_log_time_order(sample_bag: tuple) -> None:
    from rclpy.serialization import deserialize_message

    path, written = sample_bag
    messages = list(read_bag(path))
    assert [(m.log_time_ns, m.topic, m.msgtype) for m in messages] == [w[:3] for w in written]
    for message, (_, _, _, expected, data) in zip(messages, written, strict=True):
        if data is not None:
            assert message.data == data
        assert deserialize_message(message.data, type(expected)) == expected
    only = list(read_bag(path, topics=["/sample/localmap"]))
    assert [m.topic for m in only] == ["/sample/localmap"] * 2


def test_read_bag_messages_deserializes_to_rclpy_classes(
    sample_bag: tuple, fields_equal: Any
) -> None:
    path, written = sample_bag
    decoded = list(read_bag_messages(path))
    assert len(decoded) == len(written)
    for item, (stamp, topic, msgtype, message, _) in zip(decoded, written, strict=True):
        assert (item.log_time_ns, item.topic, item.msgtype) == (stamp, topic, msgtype)
        assert type(item.message) is type(message)
        fields_equal(message, item.message, msgtype)


def test_read_bag_messages_decodes_every_field_with_rosbags_too(
    sample_bag: tuple, fields_equal: Any
) -> None:
    path, written = sample_bag
    decoded = list(read_bag_messages(path, decoder="rosbags"))
    assert len(decoded) == len(written)
    for item, (stamp, topic, msgtype, message, _) in zip(decoded, written, strict=True):
        assert (item.log_time_ns, item.topic, item.msgtype) == (stamp, topic, msgtype)
        assert type(item.message) is not type(message)
        fields_equal(message, item.message, msgtype)


def test_rosbags_reader_reads_every_field(sample_bag: tuple, fields_equal: Any) -> None:
    from rosbags.rosbag2 import Reader

    path, written = sample_bag
    typestore = MessageTypes().register_custom_types()
    with Reader(path) as reader:
        assert reader.message_count == len(written)
        by_topic = {c.topic: c for c in reader.connections}
        local_map_qos = by_topic["/sample/localmap"].ext.offered_qos_profiles
        assert [q.durability.name for q in local_map_qos] == ["TRANSIENT_LOCAL"]
        assert local_map_qos[0].depth == 3
        rows = sorted(reader.messages(), key=lambda row: row[1])
        for (connection, stamp, raw), (w_stamp, topic, msgtype, message, _) in zip(
            rows, written, strict=True
        ):
            assert (connection.topic, connection.msgtype, stamp) == (topic, msgtype, w_stamp)
            fields_equal(message, typestore.deserialize_cdr(raw, msgtype), msgtype)


def test_mcap_ros2_decoder_reads_every_field(sample_bag: tuple, fields_equal: Any) -> None:
    from mcap.reader import make_reader
    from mcap_ros2.decoder import DecoderFactory

    path, written = sample_bag
    with (path / "sample_0.mcap").open("rb") as stream:
        reader = make_reader(stream, decoder_factories=[DecoderFactory()])
        assert reader.get_header().profile == "ros2"
        rows = list(reader.iter_decoded_messages(log_time_order=True))
        metadata = {record.name: record.metadata for record in reader.iter_metadata()}
    assert len(rows) == len(written)
    for (schema, channel, message, decoded), (stamp, topic, msgtype, expected, _) in zip(
        rows, written, strict=True
    ):
        assert (channel.topic, schema.name, message.log_time) == (topic, msgtype, stamp)
        assert (channel.message_encoding, schema.encoding) == ("cdr", "ros2msg")
        fields_equal(expected, decoded, msgtype)
    assert metadata["rosbag2"]["ROS_DISTRO"] == "jazzy"
    assert yaml.safe_load(metadata["rosbag2"]["serialized_metadata"])["message_count"] == len(
        written
    )


def test_schemas_and_type_hashes_match_rosidl(sample_bag: tuple) -> None:
    """The schema text names every dependency once, rosbag2 style, and each channel's type hash
    equals the one rosidl generated for the installed csam_msgs (share/csam_msgs/msg/*.json)."""
    from mcap.reader import make_reader

    path, _ = sample_bag
    with (path / "sample_0.mcap").open("rb") as stream:
        summary = make_reader(stream).get_summary()
    assert summary is not None
    share = Path(sys.prefix) / "share" / "csam_msgs" / "msg"
    for channel in summary.channels.values():
        schema = summary.schemas[channel.schema_id]
        name = schema.name.split("/")[-1]
        generated = json.loads((share / f"{name}.json").read_text())
        hashes = {t["type_name"]: t["hash_string"] for t in generated["type_hashes"]}
        assert channel.metadata["topic_type_hash"] == hashes[f"csam_msgs/msg/{name}"]
        text = schema.data.decode()
        sections = text.split("=" * 80 + "\n")
        dependencies = [s.splitlines()[0].removeprefix("MSG: ") for s in sections[1:]]
        assert len(dependencies) == len(set(dependencies)), dependencies
        for line in sections[0].splitlines():  # every complex field type is defined below
            field_type = line.split()[0].split("[")[0]
            if "/" in field_type:
                assert field_type in dependencies


def test_metadata_yaml_follows_rosbag2_version_9(sample_bag: tuple) -> None:
    path, written = sample_bag
    info = yaml.safe_load((path / "metadata.yaml").read_text())["rosbag2_bagfile_information"]
    assert info["version"] == 9
    assert info["storage_identifier"] == "mcap"
    assert info["relative_file_paths"] == ["sample_0.mcap"]
    assert info["message_count"] == len(written)
    assert info["starting_time"]["nanoseconds_since_epoch"] == written[0][0]
    assert info["duration"]["nanoseconds"] == written[-1][0] - written[0][0]
    topics = {t["topic_metadata"]["name"]: t for t in info["topics_with_message_count"]}
    local_map = topics["/sample/localmap"]
    assert local_map["message_count"] == 2
    assert local_map["topic_metadata"]["serialization_format"] == "cdr"
    (qos,) = local_map["topic_metadata"]["offered_qos_profiles"]
    assert (qos["durability"], qos["reliability"], qos["depth"]) == (
        "transient_local",
        "reliable",
        3,
    )
    assert qos["deadline"] == {"sec": 9223372036, "nsec": 854775807}


def _write_killed_bag(path: Path, flushed: int, unflushed: int) -> None:
    """A bag whose writer was never closed: ``flushed`` messages flushed, more pending."""
    from csam_msgs.msg import FeatureObservation, FeatureObservations

    bag = BagWriter(path, flush_period_s=3600)
    bag.add_topic("/robot1/features", "csam_msgs/msg/FeatureObservations")
    for label in range(flushed + unflushed):
        bag.write(
            "/robot1/features",
            (label + 1) * SECOND,
            FeatureObservations(observations=[FeatureObservation(label=label, range=1.0)]),
        )
        if label + 1 == flushed:
            bag.flush()
    bag._file.flush()  # as the OS would have it after a SIGKILL: written bytes, no footer


def test_killed_bag_reads_up_to_its_last_flushed_chunk(tmp_path: Path) -> None:
    from csam_msgs.msg import FeatureObservations
    from rclpy.serialization import deserialize_message

    path = tmp_path / "killed"
    _write_killed_bag(path, flushed=25, unflushed=10)
    info = inspect_bag(path)
    assert info.truncated_files == [path / "killed_0.mcap"]
    assert info.warnings and "cut short" in info.warnings[0]
    assert info.message_count == 25 == info.topics["/robot1/features"].message_count
    labels = [
        deserialize_message(m.data, FeatureObservations).observations[0].label
        for m in read_bag(path)
    ]
    assert labels == list(range(25))
    metadata = yaml.safe_load((path / "metadata.yaml").read_text())["rosbag2_bagfile_information"]
    assert metadata["message_count"] == 25


def test_bag_cut_inside_a_chunk_reads_the_chunks_before(tmp_path: Path) -> None:
    path = tmp_path / "cut"
    with BagWriter(path, chunk_size=100) as bag:  # many small chunks
        bag.add_topic("/counter", "std_msgs/msg/UInt32")
        for i in range(200):
            bag.write("/counter", i * SECOND, b"\x00\x01\x00\x00" + i.to_bytes(4, "little"))
    mcap = path / "cut_0.mcap"
    full = mcap.read_bytes()
    mcap.write_bytes(full[: len(full) // 2])
    (path / "metadata.yaml").unlink()
    stamps = [m.log_time_ns for m in read_bag(path)]
    assert 0 < len(stamps) < 200
    assert stamps == [i * SECOND for i in range(len(stamps))]
    assert inspect_bag(path).topics["/counter"].msgtype == "std_msgs/msg/UInt32"


def test_bag_without_metadata_reads_types_and_qos_from_mcap(sample_bag: tuple) -> None:
    path, written = sample_bag
    (path / "metadata.yaml").unlink()
    info = inspect_bag(path)
    assert not info.has_metadata
    assert info.message_count == len(written)
    local_map = info.topics["/sample/localmap"]
    assert local_map.msgtype == "csam_msgs/msg/LocalMap"
    assert [q["durability"] for q in local_map.offered_qos_profiles] == ["transient_local"]
    assert len(list(read_bag(path))) == len(written)
    assert len(list(read_bag(path / "sample_0.mcap"))) == len(written)  # the file alone


def test_writer_never_overwrites(tmp_path: Path, sample_bag: tuple) -> None:
    path, _ = sample_bag
    before = {p.name: p.read_bytes() for p in path.iterdir()}
    with pytest.raises(BagError, match="already exists"):
        BagWriter(path)
    assert {p.name: p.read_bytes() for p in path.iterdir()} == before
    blocker = tmp_path / "a_file"
    blocker.write_text("x")
    with pytest.raises(BagError, match="cannot create bag"):
        BagWriter(blocker / "bag")


def test_writer_rejects_bad_input(tmp_path: Path) -> None:
    from csam_msgs.msg import LocalMap

    with BagWriter(tmp_path / "bag") as bag:
        bag.add_topic("/robot1/local_map", "csam_msgs/LocalMap")  # short type name accepted
        with pytest.raises(BagError, match="/robot1/odom was not added"):
            bag.write("/robot1/odom", 1, b"\x00\x01\x00\x00")
        with pytest.raises(TypeError, match="holds csam_msgs/msg/LocalMap"):
            bag.write("/robot1/local_map", 1, bag)
        with pytest.raises(TypeError, match="stamp_ns must be an integer"):
            bag.write("/robot1/local_map", 1.5, LocalMap())
        with pytest.raises(ValueError, match="outside"):
            bag.write("/robot1/local_map", -1, LocalMap())
        with pytest.raises(BagError, match="already in bag"):
            bag.add_topic("/robot1/local_map", "csam_msgs/msg/LocalMap")
        with pytest.raises(ValueError, match="absolute"):
            bag.add_topic("robot1/path", "nav_msgs/msg/Path")
        with pytest.raises(LookupError, match="no_such_msgs/msg/Thing"):
            bag.add_topic("/thing", "no_such_msgs/msg/Thing")
        with pytest.raises(ValueError, match="not of the form"):
            bag.add_topic("/thing", "Thing")
    with pytest.raises(BagError, match="closed"):
        bag.write("/robot1/local_map", 1, LocalMap())


def _with_file(name: str, content: bytes) -> Any:
    def make(directory: Path) -> Path:
        (directory / name).write_bytes(content)
        return directory

    return make


@pytest.mark.parametrize(
    ("make", "message"),
    [
        (lambda directory: directory / "missing", "does not exist"),
        (lambda directory: directory, "holds no .mcap file"),
        (_with_file("x.mcap", b""), "is empty"),
        (_with_file("x.mcap", b"not an mcap file"), "not an MCAP file"),
        (_with_file("x.mcap", b"\x89MC"), "not an MCAP file"),
        (_with_file("metadata.yaml", b"[1, 2"), "not a rosbag2 metadata"),
    ],
    ids=["missing", "no-mcap", "empty", "not-mcap", "cut-in-magic", "bad-metadata"],
)
def test_reader_errors_name_the_problem(tmp_path: Path, make: Any, message: str) -> None:
    path = make(tmp_path)
    with pytest.raises(BagError, match=message):
        inspect_bag(path)
    with pytest.raises(BagError, match=message):
        list(read_bag(path))


def test_metadata_naming_a_missing_file_is_an_error(sample_bag: tuple) -> None:
    path, _ = sample_bag
    (path / "sample_0.mcap").rename(path / "elsewhere.bin")
    with pytest.raises(BagError, match="missing file"):
        inspect_bag(path)


def test_qos_conversion_follows_rosbag2() -> None:
    from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy

    latched = qos_to_dict(_transient_local(2))
    assert (latched["history"], latched["depth"], latched["durability"]) == (
        "keep_last",
        2,
        "transient_local",
    )
    best_effort = qos_to_dict(QoSProfile(depth=5, reliability=ReliabilityPolicy.BEST_EFFORT))
    # version 8 wrote the profiles as a YAML string with rmw enum numbers
    v8 = yaml.safe_dump(
        [{**latched, "history": 1, "reliability": 1, "durability": 1, "liveliness": 1}]
    )
    assert [p["durability"] for p in parse_qos_profiles(v8)] == ["transient_local"]

    recorder = subscription_qos([_transient_local(2), _transient_local(1)])
    assert recorder.durability == DurabilityPolicy.TRANSIENT_LOCAL
    assert recorder.reliability == ReliabilityPolicy.RELIABLE
    mixed = subscription_qos(
        [_transient_local(), QoSProfile(depth=5, reliability=ReliabilityPolicy.BEST_EFFORT)]
    )
    assert mixed.durability == DurabilityPolicy.VOLATILE
    assert mixed.reliability == ReliabilityPolicy.BEST_EFFORT

    player = publisher_qos([latched])
    assert (player.durability, player.reliability, player.depth) == (
        DurabilityPolicy.TRANSIENT_LOCAL,
        ReliabilityPolicy.RELIABLE,
        2,
    )
    assert publisher_qos([best_effort]).reliability == ReliabilityPolicy.BEST_EFFORT
    assert publisher_qos([]).reliability == ReliabilityPolicy.RELIABLE
    with pytest.raises(ValueError, match="lacks"):
        qos_to_dict({"depth": 1})


def test_files_of_a_bag_are_only_created_inside_it(tmp_path: Path) -> None:
    with BagWriter(tmp_path / "run" / "bag") as bag:
        bag.add_topic("/clock", "rosgraph_msgs/msg/Clock")
        bag.write("/clock", 5, b"\x00\x01\x00\x00" + bytes(8))
    assert sorted(os.listdir(tmp_path / "run" / "bag")) == ["bag_0.mcap", "metadata.yaml"]


def test_topic_recorded_with_another_definition_is_a_clear_error(sample_bag: tuple) -> None:
    """A bag from before a message definition changed: its type hash differs from the
    installed one, so that topic is refused by name, and every other topic still decodes."""
    path, written = sample_bag
    metadata = yaml.safe_load((path / "metadata.yaml").read_text())
    info = metadata["rosbag2_bagfile_information"]
    for entry in info["topics_with_message_count"]:
        if entry["topic_metadata"]["name"] == "/sample/localmap":
            entry["topic_metadata"]["type_description_hash"] = "RIHS01_" + "0" * 64
    (path / "metadata.yaml").write_text(yaml.safe_dump(metadata))
    assert inspect_bag(path).topics["/sample/localmap"].type_hash == "RIHS01_" + "0" * 64
    others = [w[1] for w in written if w[1] != "/sample/localmap"]
    assert [m.topic for m in read_bag_messages(path, topics=set(others))] == others
    with pytest.raises(BagError, match="/sample/localmap: recorded with another definition"):
        list(read_bag_messages(path))
    assert len(list(read_bag(path))) == len(written)


def _labels_read_by_rosbags_and_mcap(path: Path) -> tuple[list[int], list[int]]:
    """The labels of /robot1/features read back by rosbags' Reader and by the mcap reader."""
    from mcap.reader import make_reader
    from rosbags.rosbag2 import Reader

    typestore = MessageTypes().register_custom_types()
    with Reader(path) as reader:
        by_rosbags = [
            typestore.deserialize_cdr(raw, c.msgtype).observations[0].label
            for c, _, raw in reader.messages()
        ]
        assert reader.message_count == len(by_rosbags)
    from csam_msgs.msg import FeatureObservations
    from rclpy.serialization import deserialize_message

    (mcap_file,) = path.glob("*.mcap")
    with mcap_file.open("rb") as stream:
        by_mcap = [
            deserialize_message(message.data, FeatureObservations).observations[0].label
            for _, _, message in make_reader(stream).iter_messages(log_time_order=True)
        ]
    return by_rosbags, by_mcap


def test_killed_bag_is_recovered_into_one_rosbags_and_mcap_read(tmp_path: Path) -> None:
    """Case 8: rosbags' Reader refuses a bag cut by SIGKILL (no footer); recover_bag rewrites
    it complete, with every flushed message, and metadata.yaml counts them."""
    from rosbags.rosbag2 import Reader

    from csam_ros.bag import recover_bag

    path = tmp_path / "killed"
    _write_killed_bag(path, flushed=25, unflushed=10)
    with pytest.raises(Exception, match="magic"), Reader(path):  # noqa: PT011 - rosbags' error
        pass
    out = tmp_path / "recovered"
    report = recover_bag(path, out)
    assert report.messages == {"/robot1/features": 25}
    assert report.skipped_chunks == [] and report.cut_files == [path / "killed_0.mcap"]
    by_rosbags, by_mcap = _labels_read_by_rosbags_and_mcap(out)
    assert by_rosbags == by_mcap == list(range(25))
    info = inspect_bag(out)
    assert info.truncated_files == [] and info.warnings == []
    assert info.topics["/robot1/features"].message_count == 25
    metadata = yaml.safe_load((out / "metadata.yaml").read_text())["rosbag2_bagfile_information"]
    assert metadata["message_count"] == 25
    assert metadata["topics_with_message_count"][0]["message_count"] == 25
    with pytest.raises(BagError, match="already exists"):
        recover_bag(path, out)


def _chunk_offsets(mcap_file: Path) -> list[tuple[int, int]]:
    """(start offset, length) of every chunk record, from the file's index."""
    from mcap.reader import make_reader

    with mcap_file.open("rb") as stream:
        summary = make_reader(stream).get_summary()
    assert summary is not None
    return [(c.chunk_start_offset, c.chunk_length) for c in summary.chunk_indexes]


def _counter_bag(path: Path, n: int = 60, compression: bool = True) -> Path:
    """A bag of ``n`` UInt32 messages (value i at i s), in many small chunks."""
    with BagWriter(path, chunk_size=100, compression=compression) as bag:
        bag.add_topic("/counter", "std_msgs/msg/UInt32")
        for i in range(n):
            bag.write("/counter", i * SECOND, b"\x00\x01\x00\x00" + i.to_bytes(4, "little"))
    return path / f"{path.name}_0.mcap"


@pytest.mark.parametrize("compression", [True, False], ids=["zstd", "uncompressed"])
def test_a_damaged_chunk_is_skipped_with_a_warning(
    tmp_path: Path, compression: bool, caplog: pytest.LogCaptureFixture
) -> None:
    """Case 9: 64 bytes flipped inside a chunk: that chunk's messages are not returned (the
    CRC or the decompression fails), the reader warns with the file, offset and messages
    lost, and every other chunk reads."""
    mcap = _counter_bag(tmp_path / "counter", compression=compression)
    chunks = _chunk_offsets(mcap)
    assert len(chunks) > 3
    offset, length = chunks[2]
    data = bytearray(mcap.read_bytes())
    middle = offset + length - 16  # inside the chunk's records, before its end
    for k in range(middle - 8, middle):
        data[k] ^= 0xFF
    mcap.write_bytes(bytes(data))
    with caplog.at_level("WARNING", logger="csam_ros.bag"):
        read = [m.data for m in read_bag(mcap.parent)]
    good = {b"\x00\x01\x00\x00" + i.to_bytes(4, "little") for i in range(60)}
    assert set(read) <= good and 0 < len(read) < 60
    (warning,) = [record.getMessage() for record in caplog.records]
    handed: list[str] = []
    assert len(list(read_bag(mcap.parent, on_damage=handed.append))) == len(read)
    assert handed == [warning]
    assert str(mcap) in warning and f"offset {offset}" in warning
    lost = 60 - len(read)
    assert f"{lost} message(s) of /counter lost" in warning
    info = inspect_bag(mcap.parent)
    assert info.message_count == len(read) == info.topics["/counter"].message_count
    assert any(f"offset {offset}" in w for w in info.warnings)
    assert info.damaged_files == [mcap]


def test_metadata_may_not_name_files_outside_the_bag(tmp_path: Path, sample_bag: tuple) -> None:
    """Case 10: relative_file_paths that leave the bag directory are refused by name (the file
    outside is a valid MCAP file, which would otherwise be read)."""
    path, _ = sample_bag
    outside = tmp_path / "outside.mcap"
    outside.write_bytes((path / "sample_0.mcap").read_bytes())
    metadata = yaml.safe_load((path / "metadata.yaml").read_text())
    for name in ("../outside.mcap", str(outside), "../../../../etc/passwd"):
        metadata["rosbag2_bagfile_information"]["relative_file_paths"] = [name]
        (path / "metadata.yaml").write_text(yaml.safe_dump(metadata))
        with pytest.raises(BagError, match=f"{name}.*outside the bag directory"):
            inspect_bag(path)
        with pytest.raises(BagError, match="outside the bag directory"):
            list(read_bag(path))


def test_a_bag_cut_at_half_its_bytes_says_how_much_it_read_and_up_to_when(
    tmp_path: Path,
) -> None:
    """A complete bag whose .mcap file is cut at half its bytes (metadata.yaml intact): the
    readers return the messages of its complete chunks and say, in one line, that the file
    was cut, how many of the messages metadata.yaml lists were read and the last log time
    they reach; ``recover_bag`` says the same."""
    from csam_ros.bag import recover_bag

    mcap = _counter_bag(tmp_path / "half", n=200)
    data = mcap.read_bytes()
    mcap.write_bytes(data[: len(data) // 2])
    lines: list[str] = []
    stamps = [m.log_time_ns for m in read_bag(mcap.parent, on_damage=lines.append)]
    assert 0 < len(stamps) < 200 and stamps == [i * SECOND for i in range(len(stamps))]
    last = f"{stamps[-1] // SECOND}.000000000 s"
    expected = (
        f"read {len(stamps)} message(s) of the 200 in metadata.yaml, up to log time {last} "
        f"({stamps[-1] / SECOND:.3f} s after its first)"
    )
    assert len(lines) == 1 and f"{mcap} is cut short" in lines[0] and expected in lines[0]
    assert inspect_bag(mcap.parent).warnings == lines
    report = recover_bag(mcap.parent, tmp_path / "recovered")
    assert report.messages == {"/counter": len(stamps)}
    assert any(expected[5:] in line for line in report.lines()), report.lines()
    # the .mcap file alone has no metadata.yaml: the count read, without a total
    alone = inspect_bag(mcap).warnings
    assert len(alone) == 1 and f"read {len(stamps)} message(s), up to log time {last}" in alone[0]


def _with_metadata(path: Path, **entries: Any) -> Path:
    """``path``'s metadata.yaml with ``entries`` set in its bagfile information."""
    metadata = yaml.safe_load((path / "metadata.yaml").read_text())
    metadata["rosbag2_bagfile_information"].update(entries)
    (path / "metadata.yaml").write_text(yaml.safe_dump(metadata))
    return path


@pytest.mark.parametrize(
    ("entries", "message"),
    [
        ({"files": 5}, "metadata.yaml: files is 5, not a list"),
        ({"topics_with_message_count": 5}, "topics_with_message_count is 5, not a list"),
        ({"relative_file_paths": "counter_0.mcap"}, "relative_file_paths is 'counter_0.mcap'"),
        (
            {"relative_file_paths": ["counter_0.mcap", "./counter_0.mcap"]},
            "metadata.yaml names counter_0.mcap twice",
        ),
    ],
    ids=["files", "topics", "file-paths", "file-twice"],
)
def test_metadata_sections_of_the_wrong_kind_are_refused_by_name(
    tmp_path: Path, entries: dict[str, Any], message: str
) -> None:
    """A section that is not a list where rosbag2 writes one (a traceback in every command
    that read the bag), or a file listed twice (every message read and counted twice)."""
    bag = _with_metadata(_counter_bag(tmp_path / "counter").parent, **entries)
    with pytest.raises(BagError, match=message):
        inspect_bag(bag)
    with pytest.raises(BagError, match=message):
        list(read_bag(bag))


def test_a_message_count_beyond_any_number_is_left_out(tmp_path: Path) -> None:
    bag = _counter_bag(tmp_path / "counter").parent
    _with_metadata(bag, files=[{"path": "counter_0.mcap", "message_count": float("inf")}])
    assert inspect_bag(bag).message_count == 60


@pytest.mark.parametrize("listed", [True, False], ids=["in-metadata", "found"])
def test_a_fifo_where_a_bag_file_belongs_is_refused_at_once(tmp_path: Path, listed: bool) -> None:
    """A FIFO named ``*.mcap`` (listed in metadata.yaml or found in the directory) or named
    metadata.yaml: refused by name, never opened for a read that would wait forever."""
    from waiting import no_hang

    bag = _counter_bag(tmp_path / "counter").parent
    (bag / "counter_0.mcap").unlink()
    os.mkfifo(bag / "counter_0.mcap")
    if not listed:
        (bag / "metadata.yaml").unlink()
    with no_hang(10.0):
        with pytest.raises(BagError, match="counter_0.mcap: a FIFO, not a regular file"):
            inspect_bag(bag)
        with pytest.raises(BagError, match="counter_0.mcap: a FIFO, not a regular file"):
            list(read_bag(bag))
    if not listed:
        os.mkfifo(bag / "metadata.yaml")
        with no_hang(10.0), pytest.raises(BagError, match="metadata.yaml: a FIFO"):
            inspect_bag(bag)
