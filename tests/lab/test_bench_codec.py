"""``smartedge bench codec`` runs and prints its peers; its unbounded peer builds the same
message as the codec."""

from __future__ import annotations

import msgpack

from lab.bench import codec
from protocol import decode, encode
from protocol.codec import decode_checked, message_from_wire


def test_the_peers_decode_the_same_message() -> None:
    msg = codec._detections()
    payload = encode(msg)
    assert decode(payload) == decode_checked(payload) == message_from_wire(
        msgpack.unpackb(payload)) == msg


def test_the_bench_prints_every_peer(capsys) -> None:
    assert codec.main(["--seconds", "0.01"]) == 0
    out = capsys.readouterr().out
    assert "careful" in out and "unbounded" in out and "detections (12 kp)" in out
