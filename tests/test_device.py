import platform

from device_info import device_name

CPUINFO = """processor\t: 0
vendor_id\t: GenuineIntel
cpu family\t: 6
model\t\t: 143
model name\t: Intel(R) Xeon(R) Platinum 8480+
flags\t\t: fpu sse2 avx avx2 avx512f amx_tile

processor\t: 1
vendor_id\t: AuthenticAMD
cpu family\t: 25
model\t\t: 1
model name\t: AMD EPYC
flags\t\t: fpu sse2 avx avx2
"""


def test_cpu_name_from_cpuinfo(tmp_path):
    path = tmp_path / "cpuinfo"
    path.write_text(CPUINFO)  # the first processor names the CPU, its widest vector unit in brackets
    assert device_name("cpu", path) == "Intel(R) Xeon(R) Platinum 8480+ (family 6, model 143, AMX)"
    path.write_text(CPUINFO.split("\n\n")[1].replace(" avx2", ""))
    assert device_name("cpu", path) == "AMD EPYC (family 25, model 1)"
    path.write_text("model name\t: Some ARM core\n")
    assert device_name("cpu", path) == "Some ARM core"


def test_cpu_name_without_cpuinfo(tmp_path):
    assert device_name("cpu", tmp_path / "missing") == (platform.processor() or platform.machine() or "cpu")
