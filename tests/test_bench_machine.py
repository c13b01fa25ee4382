"""A benchmark names its CPU's generation: "AMD EPYC" alone covers machines 2-3x apart."""

from bench.machine import cpu_fields, cpu_name

CPUINFO = """processor\t: 0
vendor_id\t: AuthenticAMD
cpu family\t: 26
model\t\t: 2
model name\t: AMD EPYC
stepping\t: 1
cpu MHz\t\t: 2596.128

processor\t: 1
vendor_id\t: AuthenticAMD
cpu family\t: 25
model name\t: something else
"""


def test_the_first_processors_fields_are_read() -> None:
    fields = cpu_fields(CPUINFO)
    assert fields["cpu family"] == "26" and fields["model name"] == "AMD EPYC"


def test_the_name_carries_family_generation_and_clock() -> None:
    assert cpu_name(cpu_fields(CPUINFO)) == (
        "AMD EPYC (family 26 model 2 stepping 1, Zen 5, 2596 MHz)"
    )


def test_an_unknown_family_is_named_by_its_numbers_only() -> None:
    text = CPUINFO.replace("cpu family\t: 26", "cpu family\t: 6").replace(
        "AuthenticAMD", "GenuineIntel"
    )
    assert cpu_name(cpu_fields(text)) == "AMD EPYC (family 6 model 2 stepping 1, 2596 MHz)"


def test_without_cpuinfo_fields_the_model_name_stands_alone() -> None:
    assert cpu_name({"model name": "Some CPU"}) == "Some CPU"
