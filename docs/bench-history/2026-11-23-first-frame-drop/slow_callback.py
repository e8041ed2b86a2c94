"""Does zenoh-python buffer without bound when a subscriber's Python callback is slow?
Loopback peer pair (multicast and gossip off); a 300 KB put at up to 200 Hz for 6 s against a
callback that takes 50 ms; RSS and the publisher's put rate are printed."""
import threading, time, sys
import psutil, zenoh
from pugsd.wire.session import free_tcp_port, loopback_config, open_session, close_session

cc = zenoh.CongestionControl.BLOCK if sys.argv[1] == "block" else zenoh.CongestionControl.DROP
port = free_tcp_port()
a_cfg = loopback_config(port, []); b_cfg = loopback_config(None, [port])
for c in (a_cfg, b_cfg):
    assert c["scouting"]["multicast"]["enabled"] is False and c["scouting"]["gossip"]["enabled"] is False
a = open_session(a_cfg, require_loopback=True); b = open_session(b_cfg, require_loopback=True)
got = [0]
def cb(s):
    got[0] += 1
    time.sleep(0.05)
sub = a.declare_subscriber("zq/x", cb)
pub = b.declare_publisher("zq/x", congestion_control=cc)
time.sleep(1.0)
proc = psutil.Process()
rss0 = proc.memory_info().rss / 2**20
payload = bytes(300_000)
t0 = time.monotonic(); sent = 0; peak = rss0
while time.monotonic() - t0 < 6.0:
    pub.put(payload); sent += 1
    time.sleep(0.005)
    if sent % 50 == 0:
        peak = max(peak, proc.memory_info().rss / 2**20)
el = time.monotonic() - t0
print(f"{sys.argv[1]}: sent {sent} in {el:.1f} s ({sent/el:.0f}/s), received by then {got[0]}, RSS {rss0:.0f} -> peak {peak:.0f} MiB")
time.sleep(3); print(f"  3 s later: received {got[0]}, RSS {proc.memory_info().rss/2**20:.0f} MiB")
sub.undeclare(); pub.undeclare(); close_session(b); close_session(a)
