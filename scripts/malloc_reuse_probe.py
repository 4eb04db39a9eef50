"""Does glibc hand a freed block of a given size back to the kernel under the current
MALLOC_* environment? Prints the minor page faults of touching a fresh malloc of each size,
three times in a row: 0 after the first means the block is reused from the heap (what
training/train_shipped.sh's MALLOC_* settings are for); the full page count every time means
it is mmapped and unmapped again.

    MALLOC_MMAP_THRESHOLD_=4000000000 MALLOC_TRIM_THRESHOLD_=4000000000 \
        MALLOC_TOP_PAD_=268435456 python scripts/malloc_reuse_probe.py 600 40
"""
import argparse
import ctypes
import ctypes.util
import resource


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("mib", type=int, nargs="+", help="block sizes in MiB, probed in this order")
    ap.add_argument("--repeat", type=int, default=3)
    args = ap.parse_args()
    # All sizes checked before any is probed: a bad one is named with nothing printed before it.
    for mib in args.mib:
        if mib <= 0:
            ap.error(f"block size must be positive MiB, got {mib}")
    if args.repeat < 1:
        ap.error(f"--repeat must be at least 1, got {args.repeat}")
    libc = ctypes.CDLL(ctypes.util.find_library("c"))
    libc.malloc.restype = ctypes.c_void_p
    libc.malloc.argtypes = [ctypes.c_size_t]
    libc.free.argtypes = [ctypes.c_void_p]
    for mib in args.mib:
        n = mib << 20
        faults = []
        for _ in range(args.repeat):
            p = libc.malloc(n)
            if not p:
                raise SystemExit(f"malloc of {mib} MiB failed")
            before = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
            ctypes.memset(p, 1, n)
            faults.append(resource.getrusage(resource.RUSAGE_SELF).ru_minflt - before)
            libc.free(p)
        print(f"{mib} MiB: minor faults per touch {faults}")


if __name__ == "__main__":
    main()
