"""The shared text kernel: numbers read as Python's ``float`` reads them, bit for bit.

The kernel is recon_cli/io/_text_kernel.py via recon_cli/io/text.py: every number token reads
bit for bit as Python's ``float`` reads it; malformed tokens are refused; rows and tables come
out the same whatever the arrays' first capacity.
"""

from __future__ import annotations

import math
import struct
from decimal import Decimal, localcontext

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from recon_cli.errors import InputError
from recon_cli.io import text
from recon_cli.io._text_kernel import parse_float, scan_float, scan_int

FORMATS = [
    "%r",
    "%.17g",
    "%.16e",
    "%.9g",
    "%.6f",
    "%.10f",
    "%.0f",
    "%e",
    "%.3e",
    "%.12E",
    "%g",
    "%.25e",
    "%.40f",
    "%.30g",
]


def _bits(x: float) -> int:
    return struct.unpack("<Q", struct.pack("<d", x))[0]


def _read_all(tokens: list[str], delim: str = " ") -> np.ndarray:
    """The tokens through the row reader (fast paths and the slow path for the undecided)."""
    data = text.as_uint8(delim.join(tokens).encode())
    values, row_start, _ = text.read_rows(
        data, 0, len(data), "t.txt", delim=ord(delim) if delim != " " else 0
    )
    assert len(row_start) == 2
    return values


def _assert_identical(tokens: list[str]) -> None:
    got = _read_all(tokens)
    assert len(got) == len(tokens)
    for tok, v in zip(tokens, got.tolist(), strict=True):
        ref = float(tok)
        if math.isnan(ref):
            assert math.isnan(v)
        else:
            assert _bits(v) == _bits(ref), (tok, v, ref)


def _significant_digits(tok: str) -> int:
    mant = tok.lower().split("e")[0].lstrip("+-").replace(".", "").lstrip("0")
    return len(mant.rstrip("0")) if mant else 0


def _from_bits(b: int) -> float:
    return struct.unpack("<d", struct.pack("<Q", b))[0]


doubles = st.one_of(
    st.floats(allow_nan=False, allow_infinity=False),
    st.integers(0, (0x7FF << 52) - 1).map(
        _from_bits
    ),  # every finite bit pattern, subnormals included
    st.integers(1, (1 << 52) - 1).map(_from_bits),  # subnormals only
)


@settings(max_examples=400, deadline=None)
@given(
    xs=st.lists(
        st.tuples(doubles, st.sampled_from(FORMATS), st.booleans()), min_size=1, max_size=40
    )
)
def test_every_printed_double_reads_as_python_float_reads_it(xs):
    """Doubles printed many ways read bit for bit as ``float``; to 19 digits on the fast path."""
    tokens = []
    for x, fmt, neg in xs:
        x = -x if neg else x
        tokens.append(repr(x) if fmt == "%r" else fmt % x)
    _assert_identical(tokens)
    for tok in tokens:  # up to 19 significant digits the kernel decides alone (no slow path)
        buf = text.as_uint8(tok.encode())
        v, status = parse_float(buf, 0, len(buf))
        if _significant_digits(tok) <= 19:
            assert status == 1 and _bits(v) == _bits(float(tok)), tok


def _halfway(b: int) -> tuple[str, str]:
    """The exact decimal half way between the double of bits ``b`` and the next, two spellings.

    The exact decimal half way between the double of bits ``b`` and the next one, in two
    spellings.
    """
    x = _from_bits(b)
    y = math.nextafter(x, math.inf)
    with localcontext() as ctx:
        ctx.prec = 1200
        h = (Decimal(x) + Decimal(y)) / 2
    return format(h, "e"), format(h, "f")


@settings(max_examples=150, deadline=None)
@given(
    b=st.one_of(st.integers(1, (0x7FF << 52) - 2), st.integers(1, 1 << 53)),
    nudge=st.sampled_from(["", "1", "0000001"]),
)
def test_exact_halfway_cases_and_their_neighbours_round_as_python(b, nudge):
    """Exact half-way decimals and their nudged neighbours round as Python rounds them."""
    for tok in _halfway(b):
        if len(tok) > 1100:
            continue
        m, _, e = tok.partition("e")
        if "." not in m:
            m += "."
        _assert_identical([m + nudge + (("e" + e) if e else "")])


EDGE = [
    "0",
    "-0",
    "-0.0",
    "+0.0",
    "0e999999",
    "-0e-5",
    "00000.000000",
    "1e308",
    "1.7976931348623157e308",
    "1.7976931348623158e308",
    "1.7976931348623159e308",
    "-1e309",
    "1e400",
    "2.2250738585072014e-308",
    "2.2250738585072011e-308",
    "2.225073858507201136057409796709131975934819546351645648e-308",
    "4.9406564584124654e-324",
    "5e-324",
    "2.4703282292062327e-324",
    "2.4703282292062328e-324",
    "3e-324",
    "1e-400",
    "0.000000000000000000000000000000000001",
    "000123.4500",
    "1.",
    ".5",
    "-.5",
    "+.5e1",
    "1.e5",
    "9007199254740993",
    "9007199254740992.5",
    "18446744073709551615",
    "18446744073709551616",
    "99999999999999999999",
    "1" + "0" * 30,
    "1" + "0" * 400 + "e-400",
    "0." + "0" * 400 + "1e401",
    "3.14159265358979323846264338327950288419716939937510",
    "7.2057594037927933e16",
    "1e23",
    "8.98846567431158e307",
    "123456789012345678901234567890e-20",
    "NaN",
    "nan",
    "-nan",
    "inf",
    "-Inf",
    "+INFINITY",
    "infinity",
]


@pytest.mark.parametrize("tok", EDGE)
def test_edge_cases_read_as_python_float(tok):
    """Edge-case tokens (subnormals, overflow, long digit runs) read as ``float`` reads them."""
    _assert_identical([tok])
    buf = text.as_uint8(tok.encode())
    _, status = parse_float(buf, 0, len(buf))
    assert status in (1, 2)


BAD = [
    "",
    ".",
    "-",
    "+",
    "e5",
    ".e5",
    "1e",
    "1e+",
    "1e-",
    "1E",
    "1ex",
    "1e5.5",
    "--1",
    "+-1",
    "1.2.3",
    "0x10",
    "1_000",
    "1,5",
    "1..",
    "..1",
    "nanx",
    "infinit",
    "in",
    "na",
    "1d5",
    "1e5e5",
    "١",
]


@pytest.mark.parametrize("tok", BAD)
def test_malformed_tokens_are_refused(tok):
    """Malformed tokens are refused, and in a row they name the file and line."""
    buf = text.as_uint8(tok.encode())
    assert parse_float(buf, 0, len(buf))[1] == 0
    if tok.strip(" ,") and tok != "1,5":
        with pytest.raises(InputError, match=r"^t\.txt: line 2: "):
            data = text.as_uint8(("1 2 3\n1 " + tok + " 3\n").encode())
            text.read_rows(data, 0, len(data), "t.txt")


@pytest.mark.parametrize(
    ("tok", "ok"),
    [
        ("12", True),
        ("-7", True),
        ("+3", True),
        ("0", True),
        ("9" * 18, True),
        ("9" * 19, False),
        ("", False),
        ("-", False),
        ("1.0", False),
        ("1e3", False),
        ("x", False),
    ],
)
def test_integers(tok, ok):
    """``scan_int`` reads up to 18 digits with a sign, and refuses all else."""
    buf = text.as_uint8(tok.encode())
    v, good, stop = scan_int(buf, 0, len(buf))
    assert (good and stop == len(buf)) == ok and (not ok or v == int(tok))


@settings(max_examples=60, deadline=None)
@given(
    rows=st.lists(st.lists(doubles, min_size=3, max_size=3), min_size=1, max_size=300),
    wide=st.integers(0, 200),
)
def test_tables_do_not_depend_on_the_first_capacity(rows, wide):
    """Tables read the same from any first capacity; rows wider than it read whole."""
    body = "".join(" ".join(repr(v) for v in r) + "\n" for r in rows)
    body = "# a comment\n\n" + body + " ".join(["1"] * 3) + "\n"
    buf = text.as_uint8(body.encode())
    want = np.array([[float(repr(v)) for v in r] for r in rows] + [[1.0] * 3])
    for cap in (1, 16, 10_000):
        got = text.read_table(buf, 0, len(buf), "t.xyz", cap=cap)
        assert got.shape == want.shape and np.array_equal(got.view(np.uint64), want.view(np.uint64))
    # a row wider than any first capacity, through the variable-width reader
    line = " ".join(["2.5"] * (wide + 1)) + "\n"
    data = text.as_uint8((line + "1 2\n").encode())
    values, row_start, row_line = text.read_rows(data, 0, len(data), "t.txt")
    assert row_start.tolist() == [0, wide + 1, wide + 3] and row_line.tolist() == [1, 2]
    assert np.all(values[: wide + 1] == 2.5) and values[-2:].tolist() == [1.0, 2.0]


def test_a_row_with_other_column_count_names_its_line():
    """A row with another column count is refused, naming its line and both counts."""
    data = text.as_uint8(b"1 2 3\n\n# c\n4 5 6\n7 8\n")
    with pytest.raises(InputError, match=r"^t\.xyz: line 5: 2 columns, the first row has 3$"):
        text.read_table(data, 0, len(data), "t.xyz")


# --- eight digits at a time: the SWAR scanner must stop exactly where the digit-by-digit one did

_NON_DIGITS = [b for b in range(256) if not 48 <= b <= 57]


@pytest.mark.parametrize("run", [0, 1, 5, 7, 8, 9, 15, 16, 17, 18, 19, 24])
def test_digit_runs_stop_at_every_other_byte_with_more_bytes_after(run):
    """Digit runs of any length stop at each non-digit byte, never reading past it."""
    digits = "".join(str((7 * k + 3) % 10) for k in range(run)) or ""
    for b in _NON_DIGITS:
        if run == 0 and b in (43, 45):  # a sign: the digits after it are the number
            continue
        # 16 digits after the stop byte: the 8-byte loads see them, the scanners must not take them
        buf = text.as_uint8(digits.encode() + bytes([b]) + b"1234567890123456")
        v, ok, stop = scan_int(buf, 0, len(buf))
        assert stop == run and ok == (1 <= run <= 18), (run, b)
        if ok:
            assert v == int(digits)
        value, status, stop = scan_float(buf, 0, len(buf))
        if run and b not in (46, 69, 101):  # '.', 'e', 'E' continue a number
            assert stop == run and status in (1, 2) and (status == 2 or value == float(digits)), (
                run,
                b,
            )


@pytest.mark.parametrize("end", range(0, 21))
def test_scanners_read_no_byte_at_or_after_the_end_they_are_given(end):
    """The scanners stop at the end they are given, whatever bytes follow."""
    buf = text.as_uint8(b"12345678901234567890123.5e7 9")
    v, ok, stop = scan_int(buf, 0, end)
    assert stop == end and ok == (1 <= end <= 18) and (not ok or v == int(buf[:end].tobytes()))
    value, status, stop = scan_float(buf, 0, end)
    assert stop == end and (status == 0) == (end == 0)
    if status == 1:
        assert value == float(buf[:end].tobytes())


LONG = [
    "0.0012345678901234567",
    "-0.000012345678901234567",
    "000000000000000000001.5",
    "0.00000000000000000000123456789012345678901",
    "1234567890123456789.0",
    "12345678901234567890",
    "1.234567890123456789",
    "0.1234567890123456789",
    "00000000.000000001",
    "9999999999999999999",
    "99999999999999999999e-5",
    "0." + "0" * 30 + "7" * 19 + "e30",
]


@pytest.mark.parametrize("tok", EDGE + LONG)
def test_tokens_followed_by_more_fields_read_as_python_float(tok):
    """Tokens followed by more fields read as ``float`` reads them, and so do the fields."""
    # the tokens alone end their buffer (short ones take the byte-by-byte tail); here more
    # fields follow, so every digit run of the token goes through the 8-byte loads
    got = _read_all([tok, "1", "22", "333", "4444", "55555", "-0.25"])
    ref = float(tok)
    assert (math.isnan(got[0]) and math.isnan(ref)) or _bits(got[0]) == _bits(ref), tok
    assert got[1:].tolist() == [1.0, 22.0, 333.0, 4444.0, 55555.0, -0.25]
    if _significant_digits(tok) <= 19 and not math.isnan(ref):  # decided without the slow path
        buf = text.as_uint8((tok + " 1234567890").encode())
        v, status, stop = scan_float(buf, 0, len(buf))
        assert status == 1 and stop == len(tok) and _bits(v) == _bits(ref), tok


# 32-bit words, many of them the NaNs of float32 or the high halves of float64 NaNs
_WORDS = st.one_of(
    st.integers(0, 2**32 - 1),
    st.integers(0x7F800001, 0x7FFFFFFF),
    st.integers(0xFF800001, 0xFFFFFFFF),
    st.integers(0x7FF00000, 0x7FFFFFFF),
)


@given(st.lists(_WORDS, max_size=20), st.sampled_from(["<f4", "<f8"]))
def test_quiet_nans_makes_every_nan_quiet_and_keeps_every_other_value(words, dtype):
    """``quiet_nans`` makes a copy whose NaNs are quiet, every other value's bits kept."""
    raw = np.array(words, np.uint32)
    if dtype == "<f8":  # the words as the high halves: NaNs of both kinds and other values
        raw = (raw.astype(np.uint64) << np.uint64(32)) | np.uint64(1)
    values = raw.view(dtype)
    kept = values.copy()
    got = text.quiet_nans(values)
    assert np.array_equal(values.view(raw.dtype), raw)  # never in place
    nan = np.isnan(kept)
    assert np.array_equal(got[~nan].view(raw.dtype), kept[~nan].view(raw.dtype))
    assert np.isnan(got[nan]).all()
    with np.errstate(invalid="raise"):  # a signalling NaN would raise here
        got + 0.0
