import os
import subprocess
import sys

# allocates and frees a 100 MB tensor, then reads glibc's own account (mallinfo2): bytes in
# mmapped blocks and in the heap's free chunks
CODE = """
import ctypes, torch
from pipeline.runtime import keep_freed_memory as k
changed = (k(), k())
class Info(ctypes.Structure):
    _fields_ = [(n, ctypes.c_size_t) for n in ("arena", "ordblks", "smblks", "hblks", "hblkhd", "usmblks",
                                               "fsmblks", "uordblks", "fordblks", "keepcost")]
libc = ctypes.CDLL(None)
libc.mallinfo2.restype = Info
x = torch.ones(25_000_000)
mapped = libc.mallinfo2().hblkhd
del x
print(*changed, mapped >= 10 ** 8, libc.mallinfo2().fordblks >= 10 ** 8)
"""


def run(**env):
    base = {k: v for k, v in os.environ.items() if not k.startswith("MALLOC_")}
    out = subprocess.run([sys.executable, "-c", CODE], env={**base, **env}, capture_output=True, text=True)
    assert out.returncode == 0, out.stderr
    return out.stdout.split()


def test_freed_tensors_stay_in_the_heap_for_reuse():
    # glibc maps a 100 MB block afresh on every allocation (its pages fault in again) and unmaps it
    # when freed; kept, the freed block waits in the heap for the next tensor
    assert run() == ["True", "True", "False", "True"]  # set once per process (cached)
    # Dask's nannies set MALLOC_TRIM_THRESHOLD_=65536: overridden
    assert run(MALLOC_TRIM_THRESHOLD_="65536") == ["True", "True", "False", "True"]


def test_a_users_malloc_setting_is_left_alone():
    assert run(MALLOC_MMAP_THRESHOLD_="131072") == ["False", "False", "True", "False"]
    assert run(MALLOC_MMAP_MAX_="65536") == ["False", "False", "True", "False"]


def test_native_bfloat16_is_read_from_the_cpu_flags():
    from pipeline.runtime import native_bfloat16
    zen4 = "processor\t: 0\nflags\t\t: fpu sse2 avx2 avx512f avx512_bf16 avx512_vnni\n"
    sapphire = "flags\t\t: fpu avx512f amx_bf16 amx_tile\n"
    skylake = "processor\t: 0\nflags\t\t: fpu sse2 avx2 avx512f avx512bw\n"
    assert native_bfloat16(zen4) is True and native_bfloat16(sapphire) is True
    assert native_bfloat16(skylake) is False  # avx512 alone emulates bfloat16
    assert native_bfloat16("processor\t: 0\nFeatures\t: fp asimd\n") is None  # no x86 flags line (an ARM CPU)
    if os.path.exists("/proc/cpuinfo"):  # this machine's own answer, read from the same file
        with open("/proc/cpuinfo") as f:
            assert native_bfloat16() == native_bfloat16(f.read())
