"""The CPU named beside every result (threedq/machine.py): hand-written capabilities, in the form torch gives them,
of the CPU types the project has run on."""

from __future__ import annotations

from threedq.machine import cpu_capabilities, cpu_name, describe_cpu


def _cpu(name: str, flags: str, cores: int | None = 2) -> dict:
    cpu = {"cpu_name": name, "architecture": "x86_64", "sse2": True, "avx2": False, "avx512_f": False,
           "avx512_bf16": False, "amx_bf16": False, **{f: True for f in flags.split()}}
    if cores is not None:
        cpu["num_logical_cores"] = cores
    return cpu


class TestDescribeCpu:
    def test_the_project_machine_types(self) -> None:
        xeon = _cpu("Intel(R) Xeon(R) Processor", "avx2 avx512_f avx512_bf16 amx_bf16 amx_tile amx_int8")
        assert describe_cpu(xeon) == "Intel(R) Xeon(R) Processor (2 logical CPUs with AMX and AVX512-BF16)"
        genoa = _cpu("AMD EPYC", "avx2 avx512_f avx512_bf16")
        assert describe_cpu(genoa) == "AMD EPYC (2 logical CPUs with AVX512-BF16)"
        milan = _cpu("AMD EPYC", "avx2 fma3")
        assert describe_cpu(milan) == "AMD EPYC (2 logical CPUs with AVX2)"
        skylake = _cpu("Intel(R) Xeon(R) Gold 6148", "avx2 avx512_f avx512_bw", cores=40)
        assert describe_cpu(skylake) == "Intel(R) Xeon(R) Gold 6148 (40 logical CPUs with AVX-512)"

    def test_no_name_no_flags_no_count(self) -> None:
        assert describe_cpu({"avx2": True, "num_logical_cores": 2}) == ""  # the caller falls back
        assert describe_cpu({}) == ""
        assert describe_cpu(_cpu("Some CPU", "", cores=None)) == "Some CPU"
        assert describe_cpu(_cpu("Some CPU", "avx2", cores=None)) == "Some CPU (AVX2)"
        assert describe_cpu(_cpu("Some CPU", "avx512_f", cores=0)) == "Some CPU (AVX-512)"

    def test_this_machine(self) -> None:
        assert isinstance(cpu_capabilities(), dict)
        name = cpu_name()
        assert isinstance(name, str) and name and "\n" not in name
