"""Register codecs of the radar, the WitMotion inclinometer, the PWM module and the hopper scale."""

from __future__ import annotations

import math
import struct

import pytest
from hypothesis import given
from hypothesis import strategies as st

from protocol.errors import FieldError, ProtocolError
from protocol.registers import (
    RadarFormat,
    WeightFormat,
    decode_angle,
    decode_duty,
    decode_number,
    doppler_to_kmh,
    encode_angle,
    encode_duty,
    encode_number,
    from_kmh,
    inclinometer_span,
    kmh_to_doppler,
    registers_needed,
    to_kmh,
)

DATA_TYPES = ["uint16", "int16", "uint32", "int32", "float32"]
RANGES = {
    "uint16": (0, 0xFFFF),
    "int16": (-0x8000, 0x7FFF),
    "uint32": (0, 0xFFFFFFFF),
    "int32": (-0x80000000, 0x7FFFFFFF),
}
words = st.integers(0, 0xFFFF)


# --- generic numbers ----------------------------------------------------------------------


def test_registers_needed_per_type() -> None:
    """16-bit types take one register, 32-bit types two."""
    assert [registers_needed(t) for t in DATA_TYPES] == [1, 1, 2, 2, 2]  # type: ignore[arg-type]


def test_unknown_data_type_is_a_field_error() -> None:
    with pytest.raises(FieldError, match="unknown data_type 'int8'"):
        registers_needed("int8")  # type: ignore[arg-type]


def test_known_words_decode_as_documented() -> None:
    """Big word order = high word first (Modbus convention); little = low word first."""
    assert decode_number([0xFFFF], "int16") == -1
    assert decode_number([0xFFFF], "uint16") == 65535
    assert decode_number([0x0001, 0x0002], "uint32", "big") == 0x00010002
    assert decode_number([0x0002, 0x0001], "uint32", "little") == 0x00010002
    assert decode_number([0x4120, 0x0000], "float32") == 10.0
    assert decode_number([0x0000, 0x4120], "float32", "little") == 10.0


@pytest.mark.parametrize("data_type", DATA_TYPES)
def test_wrong_register_count_is_rejected(data_type: str) -> None:
    count = registers_needed(data_type)  # type: ignore[arg-type]
    with pytest.raises(FieldError, match="needs"):
        decode_number([0] * (count + 1), data_type)  # type: ignore[arg-type]


def test_register_values_must_be_16_bit() -> None:
    with pytest.raises(FieldError, match="not a 16-bit word"):
        decode_number([0x10000], "uint16")


def test_integer_encoding_rejects_fractions_and_overflow() -> None:
    with pytest.raises(FieldError, match="whole number"):
        encode_number(1.5, "uint16")
    with pytest.raises(FieldError, match="out of range"):
        encode_number(70000, "uint16")
    with pytest.raises(FieldError, match="out of range"):
        encode_number(-1, "uint32")
    with pytest.raises(FieldError, match="non-finite"):
        encode_number(math.nan, "float32")


@given(st.sampled_from(list(RANGES)), st.sampled_from(["big", "little"]), st.data())
def test_integer_round_trip(data_type: str, order: str, data: st.DataObject) -> None:
    lo, hi = RANGES[data_type]
    value = data.draw(st.integers(lo, hi))
    regs = encode_number(value, data_type, order)  # type: ignore[arg-type]
    assert all(0 <= r <= 0xFFFF for r in regs)
    assert decode_number(regs, data_type, order) == value  # type: ignore[arg-type]


@given(st.sampled_from(["big", "little"]), words, words)
def test_any_two_words_decode_as_float32_and_back(order: str, a: int, b: int) -> None:
    """Every bit pattern decodes; finite ones re-encode to the same words."""
    value = decode_number([a, b], "float32", order)  # type: ignore[arg-type]
    if math.isfinite(value):
        assert encode_number(value, "float32", order) == [a, b]  # type: ignore[arg-type]


# --- radar --------------------------------------------------------------------------------


def test_doppler_equation_matches_paper_a() -> None:
    """Eq. 1 by hand: f_d = 2 V cos(theta) f_i / c."""
    theta = 49.5
    v = 5.0
    f_d = 2 * v * math.cos(math.radians(theta)) * 24e9 / 1.079e9
    assert doppler_to_kmh(f_d, theta) == pytest.approx(v, rel=1e-12)
    assert kmh_to_doppler(v, theta) == pytest.approx(f_d, rel=1e-12)
    assert f_d == pytest.approx(144.4, abs=0.1)  # ~144 Hz at 5 km/h and 49.5 deg


def test_doppler_rejects_a_90_degree_mount() -> None:
    with pytest.raises(FieldError, match="mount angle"):
        doppler_to_kmh(100.0, 90.0)


@pytest.mark.parametrize(
    ("value", "unit", "kmh"), [(1.0, "km/h", 1.0), (1.0, "m/s", 3.6), (1000.0, "mm/s", 3.6)]
)
def test_units_convert_to_kmh(value: float, unit: str, kmh: float) -> None:
    assert to_kmh(value, unit, 49.5) == pytest.approx(kmh)  # type: ignore[arg-type]
    assert from_kmh(kmh, unit, 49.5) == pytest.approx(value)  # type: ignore[arg-type]


def test_default_radar_format_decodes_centi_kmh() -> None:
    """The config default: uint16 at 0.01 km/h per count."""
    assert RadarFormat().decode_kmh([525]) == pytest.approx(5.25)


def test_radar_float_nan_is_a_protocol_error() -> None:
    fmt = RadarFormat(data_type="float32", scale=1.0)
    with pytest.raises(ProtocolError, match="non-finite"):
        fmt.decode_kmh([0x7FC0, 0x0000])


def test_radar_format_rejects_zero_scale() -> None:
    with pytest.raises(FieldError, match="scale"):
        RadarFormat(scale=0.0)


@given(
    st.sampled_from(DATA_TYPES),
    st.sampled_from(["big", "little"]),
    st.sampled_from(["km/h", "m/s", "mm/s", "doppler_hz"]),
    st.floats(0.0, 30.0),
    st.floats(0.0, 80.0),
)
def test_radar_round_trip_within_resolution(
    data_type: str, order: str, unit: str, kmh: float, angle: float
) -> None:
    """encode -> decode gives the speed back to within one count of the chosen scale."""
    scale = {"km/h": 0.01, "m/s": 0.001, "mm/s": 1.0, "doppler_hz": 0.1}[unit]
    if data_type == "float32":
        scale = 1.0
    fmt = RadarFormat(data_type, order, scale, unit, angle)  # type: ignore[arg-type]
    count_kmh = to_kmh(scale, unit, angle)  # type: ignore[arg-type]
    decoded = fmt.decode_kmh(fmt.encode_kmh(kmh))
    assert abs(decoded - kmh) <= count_kmh / 2 + 1e-6 * max(1.0, kmh)


def test_radar_encoding_out_of_range_is_reported() -> None:
    with pytest.raises(FieldError, match="out of range"):
        RadarFormat(data_type="uint16", scale=0.01).encode_kmh(-1.0)


# --- inclinometer -------------------------------------------------------------------------


def test_witmotion16_register_map() -> None:
    """Roll 0x3D, pitch 0x3E, yaw 0x3F, one register each."""
    assert inclinometer_span("witmotion16", "roll") == (0x3D, 1)
    assert inclinometer_span("witmotion16", "pitch") == (0x3E, 1)
    assert inclinometer_span("witmotion16", "yaw") == (0x3F, 1)


def test_witmotion32_register_map() -> None:
    """Two registers per axis, low word first: roll 0x3D/0x3E, pitch 0x3F/0x40."""
    assert inclinometer_span("witmotion32", "roll") == (0x3D, 2)
    assert inclinometer_span("witmotion32", "pitch") == (0x3F, 2)
    assert inclinometer_span("witmotion32", "yaw") == (0x41, 2)


def test_witmotion16_scale() -> None:
    """int16 / 32768 * 180: 0x4000 is +90 deg, 0xC000 is -90 deg."""
    assert decode_angle([0x4000], "witmotion16") == pytest.approx(90.0)
    assert decode_angle([0xC000], "witmotion16") == pytest.approx(-90.0)


def test_witmotion32_scale_and_word_order() -> None:
    """int32 / 1000 with the low word first: -1.25 deg = -1250 = 0xFFFFFB1E."""
    assert decode_angle([0xFB1E, 0xFFFF], "witmotion32") == pytest.approx(-1.25)
    assert encode_angle(-1.25, "witmotion32") == [0xFB1E, 0xFFFF]


def test_unknown_axis_and_layout_are_rejected() -> None:
    with pytest.raises(FieldError, match="axis"):
        inclinometer_span("witmotion16", "heave")  # type: ignore[arg-type]
    with pytest.raises(FieldError, match="layout"):
        decode_angle([0], "wt61")  # type: ignore[arg-type]


def test_witmotion16_rejects_angles_beyond_180() -> None:
    with pytest.raises(FieldError, match="outside"):
        encode_angle(181.0, "witmotion16")


@given(st.floats(-179.99, 179.99))
def test_witmotion16_round_trip(angle: float) -> None:
    back = decode_angle(encode_angle(angle, "witmotion16"), "witmotion16")
    assert abs(back - angle) <= 180 / 32768 / 2 + 1e-12


@given(st.floats(-359.0, 359.0))
def test_witmotion32_round_trip(angle: float) -> None:
    back = decode_angle(encode_angle(angle, "witmotion32"), "witmotion32")
    assert abs(back - angle) <= 0.0005 + 1e-9


@given(st.sampled_from(["witmotion16", "witmotion32"]), st.lists(words, min_size=2, max_size=2))
def test_any_registers_decode_to_a_finite_angle(layout: str, regs: list[int]) -> None:
    """Garbage registers never crash the decoder; they give some finite angle."""
    n = inclinometer_span(layout, "roll")[1]  # type: ignore[arg-type]
    assert math.isfinite(decode_angle(regs[:n], layout))  # type: ignore[arg-type]


# --- PWM duty -----------------------------------------------------------------------------


def test_duty_units_are_tenths_of_a_percent() -> None:
    assert encode_duty(87.7) == 877
    assert encode_duty(100.0) == 1000
    assert decode_duty(481) == pytest.approx(48.1)


@pytest.mark.parametrize("pct", [-0.1, 100.01, math.nan, math.inf])
def test_out_of_range_duty_raises_instead_of_clamping(pct: float) -> None:
    with pytest.raises(FieldError, match=r"outside 0\.\.100 "):
        encode_duty(pct)


@pytest.mark.parametrize("reg", [-1, 1001, 0xFFFF])
def test_out_of_range_duty_register_raises(reg: int) -> None:
    with pytest.raises(FieldError, match=r"outside 0\.\.1000"):
        decode_duty(reg)


@given(st.integers(0, 1000))
def test_duty_register_round_trip(reg: int) -> None:
    assert encode_duty(decode_duty(reg)) == reg


@given(st.floats(0.0, 100.0))
def test_duty_percent_round_trip_within_resolution(pct: float) -> None:
    assert abs(decode_duty(encode_duty(pct)) - pct) <= 0.05 + 1e-9


def test_struct_agrees_with_float32_encoding() -> None:
    """Cross-check against struct so the word split is not tested against itself."""
    hi, lo = encode_number(3.5, "float32", "big")
    assert struct.unpack(">f", hi.to_bytes(2, "big") + lo.to_bytes(2, "big"))[0] == 3.5


def test_comm_loss_timeout_is_in_tenths_of_a_second_and_0_is_off() -> None:
    from protocol.registers import decode_comm_timeout, encode_comm_timeout

    assert encode_comm_timeout(2.0) == 20
    assert encode_comm_timeout(0.0) == 0
    assert decode_comm_timeout(20) == 2.0
    assert decode_comm_timeout(6000) == 600.0


@pytest.mark.parametrize("seconds", [-0.1, 600.1, math.nan, math.inf])
def test_out_of_range_comm_loss_timeout_raises(seconds: float) -> None:
    from protocol.registers import encode_comm_timeout

    with pytest.raises(FieldError, match="comm-loss timeout"):
        encode_comm_timeout(seconds)


def test_out_of_range_comm_loss_timeout_register_raises() -> None:
    from protocol.registers import decode_comm_timeout

    with pytest.raises(FieldError, match="comm-loss timeout register 6001"):
        decode_comm_timeout(6001)


# -- hopper scale (weight transmitter) ----------------------------------------------------------


@given(
    kg=st.floats(-100.0, 3500.0),
    data_type=st.sampled_from(["int32", "float32"]),
    word_order=st.sampled_from(["big", "little"]),
)
def test_weight_round_trips_through_its_registers(
    kg: float, data_type: str, word_order: str
) -> None:
    fmt = WeightFormat(data_type=data_type, word_order=word_order,  # type: ignore[arg-type]
                       grams_per_count=1.0, capacity_kg=3000.0)
    assert fmt.decode_kg(fmt.encode_kg(kg)) == pytest.approx(kg, abs=1e-3, rel=1e-6)


def test_weight_int32_is_high_word_first_by_default() -> None:
    assert WeightFormat().encode_kg(70.0) == [0x0001, 0x1170]  # 70 000 g
    assert WeightFormat(word_order="little").decode_kg([0x1170, 0x0001]) == 70.0


@pytest.mark.parametrize("registers", [[0x7FC0, 0x0000], [0x7F80, 0x0000], [0x4974, 0x2400]])
def test_weight_that_no_load_cell_reports_is_refused(registers: list[int]) -> None:
    fmt = WeightFormat(data_type="float32", grams_per_count=1.0, capacity_kg=500.0)
    with pytest.raises(FieldError, match="weight"):
        fmt.decode_kg(registers)  # NaN, +inf, 1e6 g = 1000 kg above 120 % of 500 kg
