#!/usr/bin/env python3
"""Hostile inputs from outside, tallied: the red-team table of issue 49's closing note.

Runs the built binary against mutated saved states, pushes, run folders, recordings, SB3
archives and a live --web session's ports, each case with a time limit, and counts per
surface: cases, accepted, clean refusals (nonzero exit, no panic), panics, hangs (time limit
hit), the largest peak RSS, and files lost (a refused case that left output under a final
name, or changed the files it was given). Standard library only; no venv needed.

    scripts/red-team.py [--bin PATH] [--quick]      # prints a Markdown table; JSON to --json
"""

import argparse
import hashlib
import json
import os
import random
import shutil
import signal
import socket
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
LIMIT_S = 30.0


class Tally:
    def __init__(self):
        self.rows = {}
        self.notes = []
        self.accepted = []

    def add(self, surface, outcome, rss_mb, lost, what):
        r = self.rows.setdefault(
            surface,
            {"cases": 0, "accepted": 0, "refused": 0, "panics": 0, "hangs": 0,
             "max_rss_mb": 0.0, "files_lost": 0, "slowest_s": 0.0},
        )
        r["cases"] += 1
        r[outcome] += 1
        r["max_rss_mb"] = max(r["max_rss_mb"], rss_mb)
        r["files_lost"] += int(lost)
        if outcome == "accepted":
            self.accepted.append(f"{surface}: {what}")
        if outcome in ("panics", "hangs") or lost:
            self.notes.append(f"{surface}: {outcome}{' + files lost' if lost else ''}: {what}")


def run(binary, args, cwd, limit=LIMIT_S, env=None):
    """(outcome, stderr, seconds, peak RSS in MB) of one command, killed at the limit."""
    start = time.monotonic()
    # GNU time measures the command's own peak RSS: rusage from wait4 here would include this
    # Python process's size at the fork (Linux keeps the pre-exec image's high-water mark).
    rss_file = tempfile.NamedTemporaryFile(prefix="rss-", delete=False)
    rss_file.close()
    timed = ["/usr/bin/time", "-q", "-f", "%M", "-o", rss_file.name] if os.path.exists(
        "/usr/bin/time") else []
    p = subprocess.Popen([*timed, binary, *args], cwd=cwd, stdout=subprocess.DEVNULL,
                         stderr=subprocess.PIPE, stdin=subprocess.DEVNULL,
                         env=env, start_new_session=True)
    # stderr is read on the side so a chatty child never blocks on a full pipe.
    chunks = []
    reader = threading.Thread(target=lambda: chunks.append(p.stderr.read()), daemon=True)
    reader.start()
    hung = False
    while True:
        pid, status, usage = os.wait4(p.pid, os.WNOHANG)
        if pid:
            break
        if time.monotonic() - start > limit:
            hung = True
            os.killpg(p.pid, signal.SIGKILL)
            pid, status, usage = os.wait4(p.pid, 0)
            break
        time.sleep(0.02)
    reader.join(5)
    err = (chunks[0] if chunks else b"").decode(errors="replace")
    secs = time.monotonic() - start
    try:
        rss = float(Path(rss_file.name).read_text().split()[-1]) / 1024.0
    except (ValueError, IndexError):
        rss = usage.ru_maxrss / 1024.0
    os.unlink(rss_file.name)
    code = os.waitstatus_to_exitcode(status)
    # GNU time exits 128 + N when the command died of signal N.
    killed = code < 0 or (timed and code > 128)
    if hung:
        return "hangs", err, secs, rss
    if "panicked" in err or killed or code == 101:
        return "panics", err, secs, rss
    return ("accepted" if code == 0 else "refused"), err, secs, rss


def digest(paths):
    h = {}
    for p in paths:
        p = Path(p)
        if p.is_file() and not p.is_symlink():
            h[str(p)] = hashlib.sha256(p.read_bytes()).hexdigest()
        elif p.is_dir():
            for q in sorted(p.rglob("*")):
                if q.is_file() and not q.is_symlink():
                    h[str(q)] = hashlib.sha256(q.read_bytes()).hexdigest()
    return h


def special_files(d, rng):
    """Things that are not regular files, where a file is expected."""
    out = {}
    fifo = d / "fifo"
    os.mkfifo(fifo)
    out["fifo"] = fifo
    out["/dev/zero"] = Path("/dev/zero")
    link = d / "zero-link"
    link.symlink_to("/dev/zero")
    out["symlink to /dev/zero"] = link
    out["/dev/null"] = Path("/dev/null")
    folder = d / "folder"
    folder.mkdir()
    out["a folder"] = folder
    empty = d / "empty"
    empty.write_bytes(b"")
    out["empty"] = empty
    sparse = d / "sparse"
    with open(sparse, "wb") as f:
        f.truncate(2 << 30)
    out["sparse 2 GiB"] = sparse
    noise = d / "noise"
    noise.write_bytes(bytes(rng.randrange(256) for _ in range(4096)))
    out["random bytes"] = noise
    return out


def mutations(text, rng, n_flips):
    """Byte-level damage to a file's bytes: cuts, flips, insertions."""
    b = text if isinstance(text, bytes) else text.encode()
    out = []
    for k in range(1, 12):
        out.append((f"cut at {k}/12", b[: len(b) * k // 12]))
    for i in range(n_flips if b else 0):
        pos = rng.randrange(len(b))
        m = bytearray(b)
        m[pos] = rng.randrange(256)
        out.append((f"byte {pos} set", bytes(m)))
    out.append(("doubled", b + b))
    out.append(("NUL inside", b[: len(b) // 2] + b"\0" + b[len(b) // 2:]))
    return out


def json_mutations(value, rng):
    """Structural damage to a JSON document: every leaf replaced by hostile values, arrays
    shortened and lengthened, keys dropped, duplicated and added."""
    hostile = [None, "x", [], {}, -1, 1e308, -1e308, 1.7976931348623157e308, 2**64, 0.5,
               True, "NaN"]
    out = []

    def paths(v, prefix=()):
        yield prefix, v
        if isinstance(v, dict):
            for k, x in v.items():
                yield from paths(x, prefix + (k,))
        elif isinstance(v, list) and v and not isinstance(v[0], (int, float)):
            for i, x in enumerate(v[:3]):
                yield from paths(x, prefix + (i,))

    def set_at(v, path, new):
        v = json.loads(json.dumps(v))
        cur = v
        for k in path[:-1]:
            cur = cur[k]
        cur[path[-1]] = new
        return v

    def delete_at(v, path):
        v = json.loads(json.dumps(v))
        cur = v
        for k in path[:-1]:
            cur = cur[k]
        del cur[path[-1]]
        return v

    for path, leaf in list(paths(value)):
        if not path:
            continue
        name = ".".join(map(str, path))
        for h in rng.sample(hostile, 4):
            out.append((f"{name} = {json.dumps(h)[:20]}", json.dumps(set_at(value, path, h))))
        if isinstance(leaf, list) and leaf:
            out.append((f"{name} one shorter", json.dumps(set_at(value, path, leaf[:-1]))))
            out.append((f"{name} one longer", json.dumps(set_at(value, path, leaf + leaf[-1:]))))
            if isinstance(leaf[0], (int, float)):
                # JSON has no NaN; Python writes it bare, which a strict reader refuses.
                bad = list(leaf)
                bad[0] = float("nan")
                out.append((f"{name}[0] = NaN", json.dumps(set_at(value, path, bad))))
        if isinstance(path[-1], str):
            out.append((f"{name} missing", json.dumps(delete_at(value, path))))
    if isinstance(value, dict) and value:
        k = next(iter(value))
        text = json.dumps(value)
        out.append((f"{k} twice", text[:-1] + f', "{k}": ' + json.dumps(value[k]) + "}"))
        out.append(("unknown key", json.dumps({**value, "surprise": 1})))
    out.append(("nested 100,000 deep", "[" * 100_000 + "]" * 100_000))
    out.append(("64 MiB of spaces", " " * (64 << 20)))
    return out


def surface_files(t, binary, work, name, args_for, good_bytes, rng, outputs, given, json_value,
                  limit=LIMIT_S, flips=40):
    """One surface: the good input mutated many ways, plus non-files."""
    cases = []
    if json_value is not None:
        cases += [(w, b.encode() if isinstance(b, str) else b)
                  for w, b in json_mutations(json_value, rng)]
    cases += mutations(good_bytes, rng, flips)
    for what, data in cases:
        d = Path(tempfile.mkdtemp(dir=work))
        target = d / "input"
        target.write_bytes(data)
        run_case(t, binary, name, what, args_for(target, d), d, outputs(d), given(target, d), limit)
    d = Path(tempfile.mkdtemp(dir=work))
    for what, special in special_files(d, rng).items():
        run_case(t, binary, name, what, args_for(special, d), d, outputs(d), [], limit)


def run_case(t, binary, surface, what, args, d, outputs, given, limit=LIMIT_S):
    before = digest(given)
    outcome, err, secs, rss = run(binary, args, ROOT, limit)
    lost = False
    if outcome != "accepted":
        # A refused case leaves nothing under an output's final name (a .partial is named so).
        lost = any(Path(o).exists() for o in outputs)
    if digest(given) != before:
        lost = True
    t.add(surface, outcome, rss, lost, f"{what}: {err.strip().splitlines()[-1:] if err else ''}")
    r = t.rows[surface]
    r["slowest_s"] = max(r["slowest_s"], secs)


def saved_states(t, binary, work, rng):
    d = Path(tempfile.mkdtemp(dir=work))
    state = d / "state.json"
    outcome, err, *_ = run(binary, ["rollout", "--checkpoint", "checkpoints/baseline", "--condition",
                                    "severe", "--episodes", "1", "--max-steps", "30", "--save-state-at", "20", str(state)],
                           ROOT, 120)
    assert state.exists(), err
    good = state.read_bytes()
    surface_files(
        t, binary, work, "saved states (record --init-state)",
        lambda p, d: ["record", "--checkpoint", "checkpoints/baseline", "--init-state", str(p),
                      "--episodes", "1", "--max-steps", "30", "--out", str(d / "out.rrd")],
        good, rng, lambda d: [d / "out.rrd"], lambda p, d: [p], json.loads(good))


def pushes(t, binary, work, rng):
    forces = ["0,40,0", "nan,0,0", "inf,0,0", "1e309,0,0", "1000.0001,0,0", "-1000,0,0", "0,0,0",
              "1,2", "1,2,3,4", "a,b,c", "", "1e-320,0,0", "707,707,0", "707,708,0"]
    steps = ["", "@0", "@1", "@1000", "@1001", "@-1", "@1e3", "@99999999999999999999"]
    bodies = ["torso", "aux_1", "floor", "world", "tail", "", "TORSO", "torso\u200b"]
    edits = []
    for f in forces:
        for s in rng.sample(steps, 3):
            edits.append(f"push:{rng.choice(bodies[:2])}={f}{s}")
    for b in bodies:
        edits.append(f"push:{b}=0,40,0@3")
    edits += [",".join(["push:torso=1000,0,0@5"] * n) for n in (2, 10, 64, 65, 1000)]
    edits += [",".join(["push:torso=600,0,0@5", "push:torso=-600,0,0@5", "push:torso=600,0,0@5"])]
    edits += ["push:torso=0,40,0@5," * 3, "push", "push:", "push:=", "push:torso=",
              "push:torso=0,40,0@5@5"]
    for e in edits:
        run_case(t, binary, "pushes (rollout --fork)", e,
                 ["rollout", "--checkpoint", "checkpoints/baseline", "--episodes", "1", "--max-steps", "20",
                  "--fork-at", "5", "--fork", e], work, [], [])


def run_folders(t, binary, work, rng):
    base = Path(tempfile.mkdtemp(dir=work)) / "run"
    replay = base.parent / "replay"
    outcome, err, *_ = run(binary, ["train", "--encoder", "none", "--steps", "600", "--learning-starts",
                                    "300", "--buffer-size", "2000", "--out", str(base),
                                    "--replay-dir", str(replay), "--quiet"], ROOT, 300)
    assert (base / "checkpoint.json").exists(), err
    files = ["checkpoint.json", "train_state.json", "model.safetensors", "metrics.jsonl"]
    for name in files:
        good = (base / name).read_bytes()
        js = json.loads(good) if name.endswith("state.json") or name == "checkpoint.json" else None

        def args_for(p, d, name=name):
            run_dir = d / "run"
            if not run_dir.exists():
                shutil.copytree(base, run_dir, symlinks=True)
                shutil.copytree(replay, d / "replay")
            target = run_dir / name
            if target.exists() or target.is_symlink():
                target.unlink()
            if p.is_file() and not p.is_symlink() and p.parent == d:
                shutil.copy(p, target)
            else:
                target.symlink_to(p.resolve() if p.is_dir() else p)
            return ["train", "--resume", str(run_dir), "--steps", "700",
                    "--replay-dir", str(d / "replay"), "--quiet"]

        surface_files(t, binary, work, "run folders (train --resume)", args_for, good, rng,
                      lambda d: [], lambda p, d: [], js, limit=60,
                      flips=10 if name == "model.safetensors" else 20)
    # replay.bin: wrong sizes and non-files; and an edited replay_dir.
    good = (replay / "replay.bin").read_bytes() if (replay / "replay.bin").exists() else None
    if good:
        for what, data in [("one byte short", good[:-1]), ("one byte more", good + b"\0"),
                           ("empty", b""), ("halved", good[: len(good) // 2])]:
            d = Path(tempfile.mkdtemp(dir=work))
            shutil.copytree(base, d / "run")
            (d / "replay").mkdir()
            (d / "replay" / "replay.bin").write_bytes(data)
            # A buffer of the wrong size is set aside (kept, renamed) and refilled: accepted,
            # and the run folder changes as any resume's does, so only the buffer is watched.
            run_case(t, binary, "run folders (train --resume)", f"replay.bin {what}",
                     ["train", "--resume", str(d / "run"), "--steps", "700", "--replay-dir",
                      str(d / "replay"), "--quiet"], d, [], [], 60)
            kept = [p for p in (d / "replay").iterdir() if p.read_bytes() == data]
            if not kept:
                t.rows["run folders (train --resume)"]["files_lost"] += 1
                t.notes.append(f"run folders: replay.bin {what} was not kept")
    d = Path(tempfile.mkdtemp(dir=work))
    shutil.copytree(base, d / "run")
    st = json.loads((d / "run" / "train_state.json").read_text())
    st["replay_dir"] = "/etc"
    (d / "run" / "train_state.json").write_text(json.dumps(st))
    run_case(t, binary, "run folders (train --resume)", "replay_dir /etc",
             ["train", "--resume", str(d / "run"), "--steps", "700", "--quiet"], d,
             ["/etc/replay.bin"], [d / "run"], 60)


def recordings(t, binary, work, rng):
    good = (ROOT / "recordings" / "baseline-severe.rrd").read_bytes()[: 2 << 20]
    env = {k: v for k, v in os.environ.items() if k not in ("DISPLAY", "WAYLAND_DISPLAY")}
    for what, data in mutations(good, rng, 30):
        d = Path(tempfile.mkdtemp(dir=work))
        p = d / "x.rrd"
        p.write_bytes(data)
        before = digest([p])
        outcome, err, secs, rss = run(binary, ["view", str(p)], ROOT, LIMIT_S, env)
        # With no display, a file view accepts ends on "no display": the file was read whole,
        # or found cut short or damaged and said so (a warning, then the viewer would open it).
        if outcome == "refused" and "no display" in err and "not whole" not in err:
            outcome = "accepted"
        t.add("recordings (view)", outcome, rss, digest([p]) != before, what)
    d = Path(tempfile.mkdtemp(dir=work))
    for what, special in special_files(d, rng).items():
        outcome, err, secs, rss = run(binary, ["view", str(special)], ROOT, LIMIT_S, env)
        t.add("recordings (view)", outcome, rss, False, what)


def sb3_archives(t, binary, work, rng):
    for model in ("sb3_baseline", "sb3_lstm"):
        good = (ROOT / "tests" / "fixtures" / f"{model}.zip").read_bytes()
        surface_files(
            t, binary, work, "SB3 archives (import-sb3)",
            lambda p, d: ["import-sb3", str(p), "--out", str(d / "out")],
            good, rng, lambda d: [d / "out"], lambda p, d: [p], None, flips=60)


def http(port, raw, timeout=10.0, read=True):
    s = socket.create_connection(("127.0.0.1", port), timeout=timeout)
    s.sendall(raw)
    data = b""
    if read:
        try:
            while True:
                b = s.recv(65536)
                if not b:
                    break
                data += b
        except (socket.timeout, ConnectionResetError):
            pass
    s.close()
    return data


def web(t, binary, work, rng):
    ports = []
    holders = [socket.socket() for _ in range(3)]
    for h in holders:
        h.bind(("127.0.0.1", 0))
        ports.append(h.getsockname()[1])
    for h in holders:
        h.close()
    env = {k: v for k, v in os.environ.items() if k not in ("DISPLAY", "WAYLAND_DISPLAY")}
    live = subprocess.Popen([binary, "live", "--web", "--checkpoint", "checkpoints/encoder-lstm",
                             "--port", str(ports[0]), "--viewer-port", str(ports[1]),
                             "--grpc-port", str(ports[2]), "--paused"], cwd=ROOT,
                            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, env=env)
    deadline = time.monotonic() + 120
    while True:
        try:
            socket.create_connection(("127.0.0.1", ports[0]), timeout=1).close()
            break
        except OSError:
            assert time.monotonic() < deadline and live.poll() is None, "live --web did not start"
            time.sleep(0.2)

    def threads_rss():
        status = Path(f"/proc/{live.pid}/status").read_text()
        th = int(next(l.split()[1] for l in status.splitlines() if l.startswith("Threads:")))
        rss = int(next(l.split()[1] for l in status.splitlines() if l.startswith("VmRSS:")))
        return th, rss / 1024.0

    def ok(port):
        try:
            r = http(port, f"GET / HTTP/1.1\r\nHost: 127.0.0.1:{port}\r\nConnection: close\r\n\r\n"
                     .encode(), timeout=10)
            return r.startswith(b"HTTP/1.1 200") or r.startswith(b"HTTP/1.0 200")
        except OSError:
            return False

    th0, rss0 = threads_rss()
    peak_rss = rss0

    def case(what, port, action):
        nonlocal peak_rss
        start = time.monotonic()
        try:
            answer = action(port)
        except OSError as e:
            answer = f"error {e}".encode()
        alive = live.poll() is None
        served = alive and ok(port)
        th, rss = threads_rss() if alive else (0, 0)
        peak_rss = max(peak_rss, rss)
        if not alive:
            outcome = "panics"
        elif answer == b"starved" or not served:
            outcome = "hangs"
        elif answer.startswith(b"HTTP/1.1 2"):
            outcome = "accepted"
            t.notes.append(f"web: accepted {what} on {port}: {answer[:80]!r}")
        else:
            outcome = "refused"
        t.add("web (live --web ports)", outcome, rss, False,
              f"{what} on {port}: {answer[:60]!r}")
        t.rows["web (live --web ports)"]["slowest_s"] = max(
            t.rows["web (live --web ports)"]["slowest_s"], time.monotonic() - start)

    host = lambda p: f"Host: 127.0.0.1:{p}\r\n"
    single = [
        ("hostile Host", lambda p: http(p, f"GET / HTTP/1.1\r\nHost: evil.example\r\nConnection: close\r\n\r\n".encode())),
        ("hostile Host case", lambda p: http(p, f"GET / HTTP/1.1\r\nHost: LOCALHOST.evil\r\nConnection: close\r\n\r\n".encode())),
        ("no Host", lambda p: http(p, b"GET / HTTP/1.1\r\nConnection: close\r\n\r\n")),
        ("17 KiB head", lambda p: http(p, f"GET / HTTP/1.1\r\n{host(p)}X: {'a' * 17408}\r\nConnection: close\r\n\r\n".encode())),
        ("8 MiB head", lambda p: http(p, f"GET / HTTP/1.1\r\n{host(p)}X: {'a' * (8 << 20)}\r\n\r\n".encode())),
        ("second request foreign Host", lambda p: http(p, f"GET / HTTP/1.1\r\n{host(p)}\r\nGET / HTTP/1.1\r\nHost: evil\r\nConnection: close\r\n\r\n".encode())),
        ("2 MiB body", lambda p: http(p, f"POST /command HTTP/1.1\r\n{host(p)}Content-Type: application/json\r\nContent-Length: {2 << 20}\r\n\r\n".encode())),
        ("chunked body", lambda p: http(p, f"POST /command HTTP/1.1\r\n{host(p)}Transfer-Encoding: chunked\r\n\r\n5\r\nhello\r\n0\r\n\r\n".encode())),
        ("garbage", lambda p: http(p, bytes(rng.randrange(256) for _ in range(4096)))),
        ("HTTP/2 preface only", lambda p: http(p, b"PRI * HTTP/2.0\r\n", timeout=8)),
        ("slow head (6 s)", lambda p: slow(p, f"GET / HTTP/1.1\r\n{host(p)}".encode(), 6.0)),
    ]
    commands = [
        ("hostile jsonx", "application/jsonx", "", '{"command":"pause"}'),
        ("hostile text/plain", "text/plain", "", '{"command":"pause"}'),
        ("hostile foreign Origin", "application/json", "Origin: http://evil.example\r\n", '{"command":"pause"}'),
        ("hostile unknown field", "application/json", "", '{"command":"pause","x":1}'),
        ("hostile key twice", "application/json", "", '{"command":"pause","command":"resume"}'),
        ("hostile push 4000 N", "application/json", "", '{"command":"push","body":"torso","force":[0,4000,0]}'),
        ("hostile push NaN", "application/json", "", '{"command":"push","body":"torso","force":[0,NaN,0]}'),
        ("hostile push 1e309", "application/json", "", '{"command":"push","body":"torso","force":[0,1e309,0]}'),
        ("hostile step 1e12", "application/json", "", '{"command":"step","count":1000000000000}'),
        ("hostile seed -1", "application/json", "", '{"command":"seed","value":-1}'),
        ("hostile scale 2", "application/json", "", '{"command":"edit","edit":"scale:hip_1=2"}'),
        ("hostile speed inf", "application/json", "", '{"command":"speed","value":1e999}'),
        ("hostile step limit 0", "application/json", "", '{"command":"step_limit","value":0}'),
        ("hostile load /etc", "application/json", "", '{"command":"load","slot":"main","dir":"/etc"}'),
        ("hostile scenario json", "application/json", "", '{"command":"scenario","json":"{\\"name\\":1}"}'),
        ("hostile fork 65 pushes", "application/json", "", '{"command":"fork","edits":"' + ",".join(["push:torso=1000,0,0@5"] * 65) + '"}'),
        ("hostile rewind far", "application/json", "", '{"command":"rewind","step":18446744073709551615}'),
        ("hostile nested", "application/json", "", "[" * 10000 + "]" * 10000),
    ]

    def slow(p, head, secs):
        s = socket.create_connection(("127.0.0.1", p), timeout=secs + 5)
        for i in range(len(head)):
            s.sendall(head[i:i + 1])
            time.sleep(secs / len(head))
            try:
                s.setblocking(False)
                got = s.recv(4096)
                s.setblocking(True)
                if got:
                    s.close()
                    return got
            except BlockingIOError:
                s.setblocking(True)
            except OSError:
                return b"closed"
        s.settimeout(secs)
        try:
            return s.recv(4096)
        except OSError:
            return b"closed"
        finally:
            s.close()

    for port in ports[:2]:
        for what, action in single:
            case(what, port, action)
    for what, ctype, extra, body in commands:
        case(what, ports[0], lambda p, c=ctype, e=extra, b=body: http(
            p, f"POST /command HTTP/1.1\r\n{host(p)}Content-Type: {c}\r\n{e}Content-Length: "
               f"{len(b.encode())}\r\nConnection: close\r\n\r\n{b}".encode()))

    # Around the guards: the servers behind them listen on no TCP port of their own, only on
    # Unix sockets in a private folder; reached there without the guard (as this user's own
    # processes could), each must still refuse.
    def listening():
        fds = Path(f"/proc/{live.pid}/fd")
        inodes = set()
        for fd in fds.iterdir():
            try:
                link = os.readlink(fd)
            except OSError:
                continue
            if link.startswith("socket:["):
                inodes.add(link[8:-1])
        tcp = []
        for table in ("/proc/net/tcp", "/proc/net/tcp6"):
            for line in Path(table).read_text().splitlines()[1:]:
                f = line.split()
                if f[3] == "0A" and f[9] in inodes:
                    tcp.append(int(f[1].split(":")[1], 16))
        unix = []
        for line in Path("/proc/net/unix").read_text().splitlines()[1:]:
            f = line.split()
            if len(f) >= 8 and int(f[3], 16) & 0x10000 and f[6] in inodes:
                unix.append(f[7])
        return sorted(tcp), unix

    tcp, unix = listening()
    t.notes.append(f"web: TCP ports listening {tcp} (public {sorted(ports)}); Unix sockets {unix}, "
                   f"folder modes {sorted({oct(os.stat(os.path.dirname(u)).st_mode & 0o777) for u in unix})}")
    for extra in sorted(set(tcp) - set(ports)):
        case("backend TCP port reached directly", extra,
             lambda p: http(p, f"GET /state HTTP/1.1\r\n{host(p)}Connection: close\r\n\r\n".encode()))

    def unix_http(path, raw):
        s = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
        s.settimeout(10)
        try:
            s.connect(path)
            s.sendall(raw)
            out = b""
            while chunk := s.recv(65536):
                out += chunk
            return out
        except OSError as e:
            return f"error {e}".encode()
        finally:
            s.close()

    for path in unix:
        name = os.path.basename(path)
        for what, raw in [
            ("no secret", b"GET /state HTTP/1.1\r\nHost: 127.0.0.1\r\nConnection: close\r\n\r\n"),
            ("guessed secret", b"GET /index.html HTTP/1.1\r\nHost: 127.0.0.1\r\nX-Gaitscope-Guard: 0\r\nConnection: close\r\n\r\n"),
            ("foreign Host", b"POST /rerun.sdk_comms.v1alpha1.MessageProxyService/ReadMessages HTTP/1.1\r\n"
                             b"Host: evil.example\r\nContent-Type: application/grpc-web+proto\r\n"
                             b"Content-Length: 0\r\nConnection: close\r\n\r\n"),
        ]:
            if name == "grpc.sock" and what != "foreign Host":
                # The proxy takes no secret (HTTP/2 frames carry none): its folder is its door,
                # and a same-user client reads the stream as it could through the public port.
                continue
            case(f"{name} reached around the guard, {what}", ports[0],
                 lambda p, path=path, raw=raw: unix_http(path, raw))

    def flood(p, make, n=200):
        socks = []
        for _ in range(n):
            try:
                s = socket.create_connection(("127.0.0.1", p), timeout=2)
                s.sendall(make(p))
                socks.append(s)
            except OSError:
                pass
        # A newcomer evicts the connection quiet longest once it has been quiet for a second:
        # a client that retries within a few seconds is served.
        started = time.monotonic()
        served = False
        while not served and time.monotonic() - started < 5:
            served = ok(p)
            if not served:
                time.sleep(0.25)
        waited = time.monotonic() - started
        for s in socks:
            s.close()
        t.notes.append(f"web: {len(socks)} connections held open on {p}: a new GET served "
                       f"{'after %.1f s' % waited if served else 'not within 5 s'}")
        return b"repelled: the page answered during the flood" if served else b"starved"

    for port in ports:
        if port == ports[2]:
            # The gRPC port speaks HTTP/2; a served GET is not what it answers, so only floods.
            continue
        case("flood of 200 idle keep-alives", port,
             lambda p: flood(p, lambda q: f"GET / HTTP/1.1\r\n{host(q)}\r\n".encode()))
        case("flood of 200 stalled HTTP/2 prefaces", port,
             lambda p: flood(p, lambda q: b"PRI * HTTP/2.0\r\n"))
        case("flood of 200 half heads", port,
             lambda p: flood(p, lambda q: b"GET / HTT"))
    # Layout changes, repeated: threads and memory must come back.
    for i in range(200):
        for body in ('{"command":"attribution","on":true}', '{"command":"attribution","on":false}'):
            http(ports[0], f"POST /command HTTP/1.1\r\n{host(ports[0])}Content-Type: application/json\r\n"
                           f"Content-Length: {len(body)}\r\nConnection: close\r\n\r\n{body}".encode())
    time.sleep(2)
    th1, rss1 = threads_rss()
    time.sleep(20)
    th2, rss2 = threads_rss()
    t.notes.append(f"web: threads {th0} at start, {th1} 2 s after every case and 400 layout "
                   f"toggles, {th2} 20 s later; RSS {rss0:.0f} → {rss1:.0f} → {rss2:.0f} MB")
    live.send_signal(signal.SIGINT)
    try:
        live.wait(20)
    except subprocess.TimeoutExpired:
        live.kill()
        t.notes.append("web: live --web did not end within 20 s of SIGINT")


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    target = os.environ.get("CARGO_TARGET_DIR", str(ROOT / "target"))
    ap.add_argument("--bin", default=f"{target}/release/gaitscope")
    ap.add_argument("--json", help="write the tally here too")
    ap.add_argument("--accepted", action="store_true", help="list the accepted cases too")
    ap.add_argument("--only", help="comma-separated surfaces: states,pushes,runs,recordings,sb3,web")
    args = ap.parse_args()
    t = Tally()
    surfaces = {"states": saved_states, "pushes": pushes, "runs": run_folders,
                "recordings": recordings, "sb3": sb3_archives, "web": web}
    chosen = args.only.split(",") if args.only else list(surfaces)
    with tempfile.TemporaryDirectory(prefix="red-team-") as work:
        for name in chosen:
            started = time.monotonic()
            # One seeded generator per surface: a surface's cases are the same run alone or
            # with the others.
            rng = random.Random(f"issue-49-{name}")
            surfaces[name](t, args.bin, Path(work), rng)
            print(f"{name}: {time.monotonic() - started:.0f} s", file=sys.stderr)
    cpu = next((l.split(":", 1)[1].strip() for l in open("/proc/cpuinfo") if l.startswith("model name")), "?")
    print(f"Red team, {time.strftime('%Y-%m-%d')}, {cpu}, each case limited to {LIMIT_S:.0f} s "
          f"(run folders 60 s):\n")
    print("| surface | cases | accepted | clean refusals | panics | hangs | peak RSS | slowest | files lost |")
    print("|---|---:|---:|---:|---:|---:|---:|---:|---:|")
    total = {k: 0 for k in ("cases", "accepted", "refused", "panics", "hangs", "files_lost")}
    for s, r in t.rows.items():
        print(f"| {s} | {r['cases']} | {r['accepted']} | {r['refused']} | {r['panics']} | {r['hangs']} "
              f"| {r['max_rss_mb']:.0f} MB | {r['slowest_s']:.1f} s | {r['files_lost']} |")
        for k in total:
            total[k] += r[k]
    print(f"| **all** | {total['cases']} | {total['accepted']} | {total['refused']} | {total['panics']} "
          f"| {total['hangs']} | | | {total['files_lost']} |")
    for n in t.notes:
        print(f"- {n}")
    if args.accepted:
        for a in t.accepted:
            print(f"  accepted: {a}")
    if args.json:
        Path(args.json).write_text(json.dumps({"rows": t.rows, "notes": t.notes, "accepted": t.accepted}, indent=1))
    return 1 if total["panics"] or total["hangs"] or total["files_lost"] else 0


if __name__ == "__main__":
    sys.exit(main())
