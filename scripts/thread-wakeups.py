#!/usr/bin/env python3
"""Wake-ups per second and CPU of every thread of a command, sampled from /proc over 20 s after
a 3 s warm-up:  scripts/thread-wakeups.py cncgw run --realtime examples/first_part.nc"""
import subprocess, time, os, sys, glob
cmd = sys.argv[1:]
p = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
time.sleep(3)
def snap():
    out = {}
    for t in glob.glob(f'/proc/{p.pid}/task/*'):
        try:
            name = open(t+'/comm').read().strip()
            st = open(t+'/status').read()
            v = int([l for l in st.splitlines() if l.startswith('voluntary_ctxt_switches')][0].split()[1])
            nv = int([l for l in st.splitlines() if l.startswith('nonvoluntary_ctxt_switches')][0].split()[1])
            f = open(t+'/stat').read().rsplit(')',1)[1].split()
            cpu = (int(f[11]) + int(f[12])) / os.sysconf('SC_CLK_TCK')
            out[t.rsplit('/',1)[1]] = (name, v + nv, cpu)
        except Exception:
            pass
    return out
a = snap(); t0 = time.time()
time.sleep(20)
b = snap(); dt = time.time() - t0
p.terminate(); p.wait()
for tid, (name, sw, cpu) in sorted(b.items(), key=lambda x: x[1][0]):
    if tid in a:
        print(f"{name:16s} wake-ups/s {(sw - a[tid][1])/dt:8.1f}  CPU {100*(cpu - a[tid][2])/dt:5.1f} %")
