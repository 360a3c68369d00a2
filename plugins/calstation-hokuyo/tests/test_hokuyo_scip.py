"""The SCIP 2.0 wire format: sums, value encodings, framing (PROTOCOLS.md's examples)."""

from __future__ import annotations

import numpy as np
import pytest
from calstation_hokuyo import scip
from hypothesis import given, strategies as st

PP_REPLY = (
    b"PP\n00P\nMODL:UTM-30LX;@\nDMIN:20;4\nDMAX:5600;_\nARES:1024;\\\nAMIN:44;7\n"
    b"AMAX:725;o\nAFRT:384;6\nSCAN:600;e\n\n"
)


def test_status_sums() -> None:
    assert scip.checksum(b"00") == b"P"
    assert scip.checksum(b"99") == b"b"


def test_kv_line_sum_leaves_out_the_semicolon() -> None:
    assert scip.kv_line("DMIN", "20") == b"DMIN:20;4\n"
    assert scip.kv_line("SCAN", "600") == b"SCAN:600;e\n"
    assert scip.kv_line("AFRT", "384") == b"AFRT:384;6\n"


def test_value_encodings() -> None:
    assert scip.encode_value(1234, 2) == b"CB"
    assert scip.encode_value(5432, 3) == b"1Dh"
    assert scip.encode_value(16_000_000, 4) == b"m2@0"
    assert scip.decode_value(b"CB") == 1234
    assert scip.decode_value(b"1Dh") == 5432
    assert scip.decode_value(b"m2@0") == 16_000_000
    with pytest.raises(ValueError):
        scip.encode_value(4096, 2)


@given(st.lists(st.integers(0, (1 << 18) - 1), max_size=200), st.sampled_from([3, 4]))
def test_values_round_trip(values: list[int], chars: int) -> None:
    data = scip.encode_values(values, chars)
    assert len(data) == chars * len(values)
    assert scip.decode_values(data, chars).tolist() == values


def test_gd_example_reply_decodes() -> None:
    rep = scip.parse_reply(b"GD0384038500\n00P\nm2@0?\n1Dh0CBB\n\n", "GD0384038500")
    assert rep.echo == b"GD0384038500"
    assert rep.status == "00"
    stamp, ranges = scip.scan_payload(rep, 3)
    assert stamp == 16_000_000
    assert ranges.tolist() == [5432, 1234]


def test_gd_example_reply_is_what_the_framing_builds() -> None:
    body = scip.with_sum(scip.encode_value(16_000_000, 4)) + scip.data_lines(
        scip.encode_values([5432, 1234], 3)
    )
    assert scip.reply(b"GD0384038500", "00", body) == b"GD0384038500\n00P\nm2@0?\n1Dh0CBB\n\n"


def test_pp_reply_parses_with_kv_sums() -> None:
    rep = scip.parse_reply(PP_REPLY, "PP", kv=True)
    fields = rep.fields()
    assert fields["DMIN"] == "20"
    assert fields["ARES"] == "1024"
    assert fields["AFRT"] == "384"
    assert fields["SCAN"] == "600"
    assert fields["MODL"] == "UTM-30LX"


def test_long_data_is_split_in_64_character_lines_and_values_straddle_them() -> None:
    values = np.arange(100, 200)  # 100 × 3 chars = 300 chars: 4 full lines + 44
    block = scip.data_lines(scip.encode_values(values, 3))
    lines = block.split(b"\n")[:-1]
    assert [len(line) for line in lines] == [65, 65, 65, 65, 45]
    for line in lines:
        assert scip.checksum(line[:-1]) == line[-1:]
    rep = scip.parse_reply(b"MD\n99b\n" + scip.with_sum(b"0000") + block + b"\n")
    assert scip.scan_payload(rep, 3)[1].tolist() == values.tolist()


def test_bad_sum_is_a_clear_error() -> None:
    with pytest.raises(scip.ScipChecksumError, match="bad sum on line b'1Dh0CBC'"):
        scip.parse_reply(b"GD0384038500\n00P\nm2@0?\n1Dh0CBC\n\n", "GD0384038500")


def test_error_status_names_its_meaning() -> None:
    err = scip.ScipStatusError("GD0000108000", "10")
    assert "laser is off" in str(err)
    assert "hardware error" in str(scip.ScipStatusError("GD", "55"))


def test_characters_outside_the_scip_range_are_rejected() -> None:
    with pytest.raises(scip.ScipProtocolError):
        scip.decode_values(b"1D\x7f", 3)
