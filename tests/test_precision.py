"""Where bf16 runs natively, and the precision a CLI run gets on a CPU without bf16 instructions."""

from __future__ import annotations

from pathlib import Path

import pytest

from threedq.pipeline import precision
from threedq.pipeline.precision import bf16_is_native, cpu_bf16_is_native, cpu_precision

AVX512 = {"architecture": "x86_64", "avx512_f": True, "avx512_bw": True, "avx512_bf16": False, "amx_bf16": False}


class TestBf16IsNative:
    def test_x86_needs_bf16_instructions(self) -> None:
        """oneDNN also 'supports' bf16 on a plain AVX-512 CPU, by converting: that is not native."""
        assert cpu_bf16_is_native(AVX512) is False
        assert cpu_bf16_is_native({**AVX512, "avx512_bf16": True}) is True
        assert cpu_bf16_is_native({**AVX512, "amx_bf16": True}) is True
        assert cpu_bf16_is_native({"architecture": "x86_64", "avx2": True}) is False
        assert bf16_is_native(AVX512) is False  # given capabilities: no GPU is considered

    def test_this_machine(self) -> None:
        assert isinstance(cpu_bf16_is_native(), bool) and isinstance(bf16_is_native(), bool)


class TestCpuPrecision:
    @pytest.mark.parametrize("asked", ["bf16-mixed", "bf16-true", "bf16"])
    def test_bf16_on_a_cpu_without_it(self, asked: str) -> None:
        got, note = cpu_precision(asked, on_cpu=True, native=False)
        assert got == "32-true" and note is not None and note.startswith(f"trainer.precision {asked} -> 32-true")

    @pytest.mark.parametrize("asked, on_cpu, native", [("bf16-mixed", True, True), ("bf16-mixed", False, False),
                                                        ("32-true", True, False), ("16-mixed", True, False),
                                                        (None, True, False), (32, True, False)])
    def test_kept(self, asked, on_cpu: bool, native: bool) -> None:
        assert cpu_precision(asked, on_cpu=on_cpu, native=native) == (asked, None)

    @pytest.mark.parametrize("native, want", [(False, "32-true"), (True, "bf16-mixed")])
    def test_cli_run(self, native: bool, want: str, tiny_dataset: Path, tmp_path: Path, capsys,
                     monkeypatch: pytest.MonkeyPatch) -> None:
        """``threedq fit --trainer.precision bf16-mixed`` on a CPU: float32 where bf16 would be emulated (pretended
        here), in the trainer and in the config the run saves; kept where the CPU has bf16 instructions."""
        from threedq.pipeline.lightning_cli import ThreeDQCLI

        monkeypatch.setattr(precision, "cpu_bf16_is_native", lambda cpu=None: native)
        cli = ThreeDQCLI(args=["--config", "stages/viewpred.yaml", f"--data.init_args.data_dir={tiny_dataset}",
                               "--trainer.accelerator=cpu", "--trainer.precision=bf16-mixed",
                               f"--trainer.default_root_dir={tmp_path}"], run=False)
        assert cli.trainer.precision == want and cli.config.trainer.precision == want
        out = capsys.readouterr().out
        assert ("[threedq] trainer.precision bf16-mixed -> 32-true" in out) == (not native)
