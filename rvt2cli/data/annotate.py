"""Add or replace the keyframe annotations of an episode file, atomically and idempotently.

The file is copied message by message into a temporary file without its old `/annotations/keyframes`
channel, the new annotation is appended, and the copy is renamed over the original. Running it twice
with the same keyframes gives a byte-identical file.
"""

import io
from pathlib import Path

from mcap.reader import make_reader

from rvt2cli.atomic import atomic_open
from rvt2cli.data import topics
from rvt2cli.data.keyframes import KeyframeAnnotation
from rvt2cli.data.reader import _check_readable, iter_raw_messages, read_metadata
from rvt2cli.data.writer import McapChannels


def write_keyframes(path: str | Path, annotation: KeyframeAnnotation) -> None:
    path = Path(path)
    data = _check_readable(path)
    read_metadata(path, data)  # refuses foreign files and newer versions before anything is written
    metadata = list(make_reader(io.BytesIO(data)).iter_metadata())
    with atomic_open(path) as f:
        out = McapChannels(f)
        for msg in iter_raw_messages(path, data):
            if msg.topic == topics.KEYFRAMES:
                continue
            out.write_raw(msg.topic, msg.schema_name, msg.schema_encoding, msg.schema_data,
                          msg.message_encoding, msg.data, msg.log_time, msg.publish_time)
        out.write_keyframes(annotation, str(path))
        for record in metadata:
            out.writer.add_metadata(record.name, record.metadata)
        out.finish()
