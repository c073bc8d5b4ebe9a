"""The CPU named beside every result (threedq/machine.py): hand-written /proc/cpuinfo texts of the CPU types the
project has run on."""

from __future__ import annotations

from threedq.machine import cpu_name, describe_cpu


def _cpuinfo(model: str, flags: str, processors: int = 2) -> str:
    block = f"processor\t: {{n}}\nvendor_id\t: x\nmodel name\t: {model}\nflags\t\t: fpu sse sse2 {flags}\n\n"
    return "".join(block.format(n=n) for n in range(processors))


class TestDescribeCpu:
    def test_the_project_machine_types(self) -> None:
        xeon = _cpuinfo("Intel(R) Xeon(R) Processor", "avx2 avx512f avx512_bf16 amx_bf16 amx_tile amx_int8")
        assert describe_cpu(xeon, 2) == "Intel(R) Xeon(R) Processor (2 logical CPUs with AMX and AVX512-BF16)"
        genoa = _cpuinfo("AMD EPYC", "avx2 avx512f avx512_bf16")
        assert describe_cpu(genoa, 2) == "AMD EPYC (2 logical CPUs with AVX512-BF16)"
        milan = _cpuinfo("AMD EPYC", "avx2 fma")
        assert describe_cpu(milan, 2) == "AMD EPYC (2 logical CPUs with AVX2)"
        skylake = _cpuinfo("Intel(R) Xeon(R) Gold 6148", "avx2 avx512f avx512bw")
        assert describe_cpu(skylake, 40) == "Intel(R) Xeon(R) Gold 6148 (40 logical CPUs with AVX-512)"

    def test_no_model_name_no_flags_no_count(self) -> None:
        assert describe_cpu("processor\t: 0\nflags\t: avx2\n", 2) == ""  # e.g. an ARM cpuinfo: the caller falls back
        assert describe_cpu(_cpuinfo("Some CPU", ""), None) == "Some CPU"
        assert describe_cpu(_cpuinfo("Some CPU", "avx2"), None) == "Some CPU (AVX2)"
        assert describe_cpu(_cpuinfo("Some CPU", "avx512f"), 0) == "Some CPU (AVX-512)"

    def test_this_machine(self) -> None:
        name = cpu_name()
        assert isinstance(name, str) and name and "\n" not in name
