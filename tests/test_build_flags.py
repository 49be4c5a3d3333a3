"""The extension's compiler flags (torch_rbpt/build_flags.py): the target and the tuning setup.py
chooses for the build machine."""
import pytest

from torch_rbpt import build_flags

INTEL = "vendor_id\t: GenuineIntel\nmodel name\t: Intel(R) Xeon(R) Processor\nflags\t\t: fpu sse2 avx2 avx512f avx512bw\n"
INTEL_AVX2 = "vendor_id\t: GenuineIntel\nflags\t\t: fpu sse2 avx2 fma\n"
AMD = "vendor_id\t: AuthenticAMD\nflags\t\t: fpu sse2 avx2 avx512f avx512bw\n"
SPR_TUNING = ["-mtune=sapphirerapids", "-mprefer-vector-width=512"]


def test01_intel_avx512_unaffected_by_gds_is_tuned():
    assert build_flags.host_tuning(INTEL, "Not affected\n") == SPR_TUNING
    # Several processors: the first's fields count.
    assert build_flags.host_tuning(INTEL + "\n" + INTEL, "Not affected") == SPR_TUNING


@pytest.mark.parametrize("cpuinfo, gds", [
    (INTEL, "Mitigation: Microcode"),        # gathers slowed by the microcode
    (INTEL, "Vulnerable: No microcode"),
    (INTEL_AVX2, "Not affected"),            # no AVX-512
    (AMD, "Not affected"),                   # Zen: hardware gathers measured slower
    ("", "Not affected"),
])
def test02_other_cpus_keep_gccs_tuning(cpuinfo, gds):
    assert build_flags.host_tuning(cpuinfo, gds) == []


def test03_target_flags(monkeypatch):
    monkeypatch.delenv("MARCH", raising=False)
    monkeypatch.delenv("MTUNE", raising=False)
    monkeypatch.setattr(build_flags, "host_tuning", lambda: SPR_TUNING)
    assert build_flags.target_flags() == ["-march=native", *SPR_TUNING]
    # Another target than this machine: no host tuning.
    assert build_flags.target_flags("x86-64-v3") == ["-march=x86-64-v3"]
    monkeypatch.setenv("MARCH", "x86-64-v3")
    assert build_flags.target_flags() == ["-march=x86-64-v3"]
    # MTUNE forces the tuning, alone.
    monkeypatch.setenv("MTUNE", "generic")
    assert build_flags.target_flags("native") == ["-march=native", "-mtune=generic"]
    assert build_flags.tuned_for(build_flags.target_flags("native")) == "generic"
    assert build_flags.tuned_for(["-march=native"]) == ""

