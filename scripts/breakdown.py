#!/usr/bin/env python3
# Where a transaction's instructions go, by mbgate's own code (scripts/breakdown runs
# it; docs/performance.md "A transaction on a quiet line"). Reads two callgrind files
# of the same gateway binary (built with line tables), runs of N1 and N2 transactions
# made with --dump-instr=yes, and prints their difference a transaction:
#   - each instruction's cost goes to the innermost frame of src/ in its inline chain
#     (llvm-addr2line -i on the binary), so code inlined from std or tokio into a
#     function of ours is that function's;
#   - the cost of code outside src/ (tokio, std, bytes, libc) goes to the src/ frames
#     that called it, in proportion to each call's inclusive cost, up the call graph;
#   - what no src/ frame calls is the runtime's own loop: its waits (`park`: epoll_wait,
#     timers, readiness) and its tasks (polls, wakes, scheduling);
#   - every owner is put in a stage of a transaction by its file and function (STAGES).
# Usage: breakdown.py [--by stage|fn|file] [--top K] TRANSACTIONS BINARY CG.N1 CG.N2
import collections
import json
import re
import subprocess
import sys

# The mbgate source files: their path from the repository, after `/src/`.
SRC_MARK = '/src/'


def parse(path):
    """The self cost of each (object, function, address), and each call's site and
    inclusive cost."""
    names = {}
    ob = fn = None
    addr = 0
    line = 0
    self_cost = collections.defaultdict(lambda: None)
    calls = []
    events = None
    pending = None
    cob = cfn = None

    def name(kind, rest):
        m = re.match(r'\((\d+)\)(?: (.*))?$', rest)
        if not m:
            return rest
        k = (kind, m.group(1))
        if m.group(2) is not None:
            names[k] = m.group(2)
        return names.get(k, rest)

    def pos(tok, cur):
        if tok == '*':
            return cur
        if tok[0] in '+-':
            return cur + int(tok)
        return int(tok, 0)

    for raw in open(path, errors='replace'):
        raw = raw.rstrip('\n')
        if not raw:
            continue
        c0 = raw[0]
        if c0.isdigit() or c0 in '+-*':
            parts = raw.split()
            addr = pos(parts[0], addr)
            line = pos(parts[1], line)
            costs = [int(x) for x in parts[2:]]
            if pending is not None:
                calls.append((ob, fn, addr, pending[0], pending[1], costs))
                pending = None
            else:
                cur = self_cost[(ob, fn, addr)]
                if cur is None:
                    self_cost[(ob, fn, addr)] = costs
                else:
                    cur.extend([0] * (len(costs) - len(cur)))
                    for i, c in enumerate(costs):
                        cur[i] += c
            continue
        if raw.startswith('events:'):
            events = raw.split()[1:]
        elif raw.startswith('ob='):
            ob = name('ob', raw[3:])
            cob = None
        elif raw.startswith(('fl=', 'fi=', 'fe=')):
            name('fl', raw[3:])
        elif raw.startswith('fn='):
            fn = name('fn', raw[3:])
            cob = None
        elif raw.startswith('cob='):
            cob = name('ob', raw[4:])
        elif raw.startswith(('cfi=', 'cfl=')):
            name('fl', raw[4:])
        elif raw.startswith('cfn='):
            cfn = name('fn', raw[4:])
        elif raw.startswith('calls='):
            pending = (cob or ob, cfn)
            cob = None
    return events, self_cost, calls


def short(fn):
    fn = re.sub(r'::h[0-9a-f]{16}$', '', fn)
    for a, b in (('$LT$', '<'), ('$GT$', '>'), ('$u7b$', '{'), ('$u7d$', '}'), ('$u20$', ' '), ('..', '::')):
        fn = fn.replace(a, b)
    return fn


def owners(binary, addrs):
    """Each address's innermost src/ frame (file, function), or None. The command
    line's and the gateway's entry (src/cli/, gateway.rs, main.rs) are the runtime's."""
    out = {}
    addrs = sorted(addrs)
    p = subprocess.run(['llvm-addr2line', '-i', '-f', '-C', '--output-style=JSON', '-e', binary],
                       input=''.join(f'{a:#x}\n' for a in addrs), capture_output=True, text=True, check=True)
    for a, row in zip(addrs, p.stdout.splitlines()):
        found = None
        for fr in json.loads(row).get('Symbol', []):
            loc = fr.get('FileName', '')
            if SRC_MARK in loc and '/.cargo/' not in loc and '/rustc/' not in loc and '/deps/' not in loc:
                f = 'src/' + loc.rsplit(SRC_MARK, 1)[1]
                if not (f.startswith('src/cli/') or f in ('src/gateway.rs', 'src/main.rs')):
                    found = (f, short(fr.get('FunctionName', '')))
                break
        out[a] = found
    return out


def add(a, b, k=1.0):
    if len(a) < len(b):
        a.extend([0.0] * (len(b) - len(a)))
    for i, x in enumerate(b):
        a[i] += x * k


def attribute(binary, path):
    events, self_cost, calls = parse(path)
    name = binary.rsplit('/', 1)[-1]
    obs = {o for (o, _, _) in self_cost if o and o.rsplit('/', 1)[-1] == name}
    addrs = {a for (o, _, a) in self_cost if o in obs} | {a for (o, _, a, _, _, _) in calls if o in obs}
    own = owners(binary, addrs)
    outside = collections.defaultdict(list)
    result = collections.defaultdict(list)
    for (o, f, a), c in self_cost.items():
        w = own.get(a) if o in obs else None
        add(result[w] if w else outside[(o, f)], c)
    callers = collections.defaultdict(list)
    for (o, f, a, co, cf, c) in calls:
        w = own.get(a) if o in obs else None
        callers[(co, cf)].append((('own', w) if w else ('fn', (o, f)), c[0] if c else 0))
    memo = {}

    def spread(key, depth=0):
        if key in memo:
            return memo[key]
        fn = key[1] or ''
        if 'Context::park' in fn or 'time::Driver::park' in fn or 'io::driver::Driver::turn' in fn:
            memo[key] = {('runtime', 'park'): 1.0}
            return memo[key]
        memo[key] = {('runtime', 'tasks'): 1.0}  # a cycle, or the top of the call graph
        cs = callers.get(key, [])
        total = sum(ir for _, ir in cs)
        if total <= 0 or depth > 40:
            return memo[key]
        d = collections.defaultdict(float)
        for (kind, who), ir in cs:
            if ir <= 0 or who == key:
                continue
            if kind == 'own':
                d[who] += ir / total
            else:
                for k, v in spread(who, depth + 1).items():
                    d[k] += v * ir / total
        s = sum(d.values())
        if s:
            memo[key] = {k: v / s for k, v in d.items()}
        return memo[key]

    for key, c in outside.items():
        for k, share in spread(key).items():
            add(result[k], c, share)
    return events, result


def has(f, fn, files, fns=None):
    return any(x in f for x in files) and (fns is None or any(y in fn for y in fns))


# The stages of a transaction, by the file and function that own the cost; the first
# rule that holds decides.
STAGES = [
    ('metrics', lambda f, fn: has(f, fn, ['relay/telemetry.rs', 'ops/metrics/', 'ops/stats.rs', 'ops/capture/hub.rs'])
        or has(f, fn, ['line/relay/mod.rs'], ['tell'])),
    ('read (master socket)', lambda f, fn: has(f, fn, ['masters/tcp/reader.rs'], ['read_loop', 'async_fn', 'async_block', 'closure', 'echo_in'])
        or has(f, fn, ['masters/tcp/udp.rs'], ['recv', 'async', 'closure'])),
    ('parse', lambda f, fn: has(f, fn, ['masters/tcp/codec.rs', 'frame/mbap.rs'], ['decode'])
        or has(f, fn, ['frame/pdu.rs'], ['check_request']) or has(f, fn, ['masters/tcp/rtu.rs'])),
    ('admit', lambda f, fn: has(f, fn, ['masters/tcp/reader.rs', 'masters/access/', 'masters/router.rs', 'relay/command.rs'])
        or has(f, fn, ['outbox/queue.rs'], ['Command'])
        or has(f, fn, ['relay/admit.rs'], ['on_command', 'on_request', 'cached'])
        or has(f, fn, ['relay/pending.rs'], ['new', 'boxed']) or has(f, fn, ['line/outbox/mod.rs'], ['ticket'])
        or has(f, fn, ['relay/cache.rs'], ['get', 'acted_on', 'stamp'])),
    ('queue', lambda f, fn: has(f, fn, ['relay/scheduler/', 'relay/admit.rs'])
        or (has(f, fn, ['relay/pending.rs']) and 'deliver' not in fn)),
    ('line write', lambda f, fn: has(f, fn, ['relay/transmit.rs', 'relay/outgoing.rs'])
        or has(f, fn, ['relay/line/mod.rs'], ['encode', 'allocate', 'wrote', 'pause_after', 'has_room'])
        or has(f, fn, ['relay/line/mbap/mod.rs'], ['encode', 'sent', 'of', 'wrote', 'allocate', 'has_room', 'paused_until'])
        or has(f, fn, ['relay/line/serial/mod.rs'], ['encode', 'wrote', 'allocate', 'has_room', 'drained'])
        or has(f, fn, ['relay/tids.rs'], ['allocate', 'set', 'step'])
        or has(f, fn, ['relay/inflight.rs'], ['start', 'response_timeout', 'policy'])
        or has(f, fn, ['port/serial/stream.rs'], ['Writer', 'write'])
        or has(f, fn, ['port/fd.rs'], ['write']) or has(f, fn, ['frame/rtu.rs', 'frame/serial.rs'], ['encode'])
        or has(f, fn, ['port/kind.rs', 'port/serial/mod.rs'], ['wire_time'])),
    ('line read (port, wait)', lambda f, fn: has(f, fn, ['relay/event.rs', 'port/fd.rs', 'port/serial/stream.rs', 'port/serial/timer.rs', 'port/lifecycle.rs', 'relay/opening.rs'])
        or has(f, fn, ['relay/line/mod.rs', 'relay/line/mbap/mod.rs'], ['received', 'heard', 'next_wake', 'set_tape'])
        or has(f, fn, ['relay/line/serial/'], ['received', 'accept', 'strip_echo', 'next_wake', 'quiet_after', 'free_at'])
        or has(f, fn, ['frame/framer.rs', 'frame/resync/', 'frame/serial.rs'], ['push', 'pause', 'buffered', 'clear'])
        or has(f, fn, ['ops/capture/dropped.rs'], ['push', 'skip'])),
    ('match', lambda f, fn: has(f, fn, ['relay/replies.rs', 'relay/inflight.rs', 'relay/line/', 'relay/tids.rs', 'relay/cache.rs',
                                        'relay/learn.rs', 'frame/', 'ops/capture/dropped.rs'])),
    ('reply write', lambda f, fn: has(f, fn, ['relay/pending.rs', 'line/outbox/', 'masters/tcp/writer.rs', 'masters/tcp/codec.rs'])),
    ('relay loop', lambda f, fn: has(f, fn, ['line/relay/mod.rs', 'relay/failures.rs', 'relay/watchdog.rs'])),
    ('connection', lambda f, fn: has(f, fn, ['masters/tcp/connection.rs', 'line/woken.rs', 'masters/tcp/dial.rs', 'masters/tcp/echo.rs'])),
]


def stage(owner):
    if owner[0] == 'runtime':
        return {'park': 'runtime: park (epoll_wait, timers, readiness)'}.get(owner[1], 'runtime: tasks (polls, wakes, scheduling)')
    for name, rule in STAGES:
        if rule(*owner):
            return name
    return 'other: ' + owner[0]


def main():
    args = sys.argv[1:]
    by, top = 'stage', 30
    while args and args[0].startswith('--'):
        if args[0] == '--by':
            by = args[1]
        elif args[0] == '--top':
            top = int(args[1])
        args = args[2:]
    n, binary, first, second = int(args[0]), args[1], args[2], args[3]
    events, a = attribute(binary, first)
    _, b = attribute(binary, second)
    per = {}
    for k in set(a) | set(b):
        x, y = a.get(k, []), b.get(k, [])
        m = max(len(x), len(y))
        x, y = list(x) + [0] * (m - len(x)), list(y) + [0] * (m - len(y))
        per[k] = [(q - p) / n for p, q in zip(x, y)]
    groups = collections.defaultdict(list)
    for k, v in per.items():
        g = stage(k) if by == 'stage' else (k[0] if by == 'file' else f'{k[0]} {k[1]}')
        add(groups[g], v)
    total = [sum(v[i] if i < len(v) else 0 for v in groups.values()) for i in range(len(events))]
    print('| ' + by + ' | ' + ' | '.join(events) + ' |')
    print('|---|' + '---:|' * len(events))
    rows = sorted(groups.items(), key=lambda kv: -kv[1][0])
    for g, v in rows[:top]:
        if abs(v[0]) >= 1:
            print(f'| {g} | ' + ' | '.join(f'{x:.0f}' if abs(x) >= 10 else f'{x:.1f}' for x in v) + ' |')
    print('| total | ' + ' | '.join(f'{x:.0f}' if abs(x) >= 10 else f'{x:.1f}' for x in total) + ' |')


main()
