import ctypes, sys, threading
from pugsd.daemon.app import apply_malloc_arena_max
n = int(sys.argv[1])
print("applied", apply_malloc_arena_max(n), file=sys.stderr)
libc = ctypes.CDLL("libc.so.6")
libc.malloc.restype = ctypes.c_void_p
libc.malloc.argtypes = [ctypes.c_size_t]
libc.free.argtypes = [ctypes.c_void_p]
held = []
def work():
    held.append([libc.malloc(4096) for _ in range(64)])
ts = [threading.Thread(target=work) for _ in range(6)]
for t in ts: t.start()
for t in ts: t.join()
sys.stderr.flush()
libc.malloc_stats()
