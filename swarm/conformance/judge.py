"""Each clause's verdict from the cases' evidence (the recording, the processes' exit
statuses and times, what the kit did and saw). A verdict's text is its evidence: the
numbers it was decided on."""

from __future__ import annotations

import re
from collections.abc import Callable

import numpy as np

from swarm.conformance.clauses import CLAUSES
from swarm.conformance.evidence import Evidence, estimate_arrays
from swarm.conformance.kit import CaseRun, Kit
from swarm.conformance.report import ERROR, FAIL, NOT_CLAIMED, NOT_RUN, PASS, Verdict
from swarmrt.protocol import DROP_BATCH, DROP_ESTIMATE, message_dropped

__all__ = ["judge_all", "JUDGES"]


class Inconclusive(Exception):
    """The case did not create the situation the clause is about (the kit's failure, not
    the agent's)."""


Judgement = tuple[bool, str]
JUDGES: dict[str, tuple[tuple[str, ...], Callable[[Kit], Judgement]]] = {}


def judges(cid: str, *cases: str):
    def deco(fn):
        JUDGES[cid] = (cases, fn)
        return fn

    return deco


def judge_all(kit: Kit) -> list[Verdict]:
    out = []
    for c in CLAUSES:
        cases, fn = JUDGES[c.id]
        if c.claim is not None and c.claim not in kit.claims:
            out.append(Verdict.of(c.id, NOT_CLAIMED, f"not claimed (--claims {c.claim} to check it)"))
            continue
        missing = [n for n in cases if n not in kit.runs]
        if missing:
            out.append(Verdict.of(c.id, NOT_RUN, f"case {', '.join(missing)} not run"))
            continue
        broken = [kit.runs[n] for n in cases if kit.runs[n].error]
        if broken:
            out.append(Verdict.of(c.id, ERROR, f"case {broken[0].name} could not run: {broken[0].error} "
                                  f"(logs: {broken[0].out / 'logs'})", "+".join(cases)))
            continue
        try:
            ok, text = fn(kit)
            out.append(Verdict.of(c.id, PASS if ok else FAIL, text, "+".join(cases)))
        except Inconclusive as exc:
            out.append(Verdict.of(c.id, ERROR, f"inconclusive: {exc}", "+".join(cases)))
    return out


# -- helpers ------------------------------------------------------------------------------------
def _ev(kit: Kit, case: str) -> Evidence:
    ev = kit.runs[case].ev
    assert ev is not None
    return ev


def _live_steps(kit: Kit, ev: Evidence) -> list[int]:
    return [k for k in ev.steps() if kit.sat in ev.clocks[k][1]]


def _ranges(ks: list[int]) -> str:
    """[1, 2, 3, 7] -> '1-3, 7'."""
    if not ks:
        return "none"
    out, start, prev = [], ks[0], ks[0]
    for k in [*ks[1:], None]:
        if k is not None and k == prev + 1:
            prev = k
            continue
        out.append(f"{start}" if start == prev else f"{start}-{prev}")
        if k is not None:
            start = prev = k
    return ", ".join(out)


def _complete(kit: Kit, ev: Evidence) -> str | None:
    """None if the run reached its end (the done clock after every step), else why not."""
    if ev.done_clock_ns is None:
        return f"the run did not end (last clock: step {max(ev.clocks, default=-1)} of {kit.K - 1})"
    missing = [k for k in range(kit.K) if k not in ev.clocks]
    if missing:
        return f"no clock of steps {_ranges(missing)}"
    return None


def _meas_arrays(m) -> bytes:
    return b"".join(np.asarray(a, dtype=float).tobytes() for a in (m.target, m.camera, m.q_BjBi, m.r_ij_Bi_m, m.R_Bi.data))


def _same_numbers(kit: Kit, ev: Evidence) -> tuple[list[int], list[int]]:
    """(steps equal to the clean run bit for bit, steps that differ or are missing), over
    agent i's posterior estimates and measurement batches."""
    ref = _ev(kit, "clean")
    same: list[int] = []
    diff: list[int] = []
    for k in range(kit.K):
        a, b = ev.posterior(k), ref.posterior(k)
        ma, mb = ev.meas.get(k), ref.meas.get(k)
        ok = (a is not None and b is not None and estimate_arrays(a).tobytes() == estimate_arrays(b).tobytes()
              and ((ma is None and mb is None) or (ma is not None and mb is not None
                                                   and _meas_arrays(ma[0][0]) == _meas_arrays(mb[0][0]))))
        (same if ok else diff).append(k)
    return same, diff


def _world_timeouts(run: CaseRun, sat: int) -> list[int]:
    """Steps whose estimate (or report) of ``sat`` the world gave up waiting for (its log)."""
    path = run.out / "logs" / "world.log"
    if not path.exists():
        return []
    out = []
    # (The world waits for each agent's health report, the step's last message, since
    # 2026-12-07; before, for its estimate: either line.)
    pattern = r"step (\d+): no (?:estimate|health report \(the step's last message\)) from \[([0-9, ]*)\]"
    for m in re.finditer(pattern, path.read_text(errors="replace")):
        if str(sat) in [x.strip() for x in m[2].split(",")]:
            out.append(int(m[1]))
    return out


def _slowest(ev: Evidence) -> tuple[int, float]:
    gaps = ev.clock_gaps_s()
    return max(gaps, key=lambda g: g[1]) if gaps else (-1, 0.0)


def _code(c: int | None) -> str:
    if c is None:
        return "still running"
    return f"exit {c}" if c >= 0 else f"killed by signal {-c}"


# -- the clauses ----------------------------------------------------------------------------------
@judges("C1", "clean")
def c1(kit: Kit) -> Judgement:
    run, ev = kit.runs["clean"], _ev(kit, "clean")
    ups = [t for a, t in ev.token_events() if a]
    sent = sum(ev.from_me.values())
    sec = "its credential accepted by the router (security on)" if run.sc and run.sc.emulator.security else "security off"
    if not ups and not sent:
        return False, (f"never on the bus: no token, no message from {kit.name} ({_code(run.agent_code)}; "
                       f"see {run.out / 'logs' / (kit.name + '.log')})")
    return bool(ups and sent), f"connected as {kit.name}, {sec}: its token and {sent} messages signed {kit.name}"


@judges("C2", "clean")
def c2(kit: Kit) -> Judgement:
    ev = _ev(kit, "clean")
    evs = ev.token_events()
    if not evs or 0 not in ev.clocks:
        return False, f"token events {len(evs)}, step 0 {'seen' if 0 in ev.clocks else 'never came'}"
    up = next((t for a, t in evs if a), None)
    if up is None:
        return False, "its token never appeared"
    t0 = ev.clocks[0][0]
    end = ev.done_clock_ns or max(t for t, _l in ev.clocks.values())
    drops = [t for a, t in evs if not a and up < t <= end]
    ok = up < t0 and not drops
    return ok, (f"token up {(t0 - up) / 1e9:.2f} s before step 0's clock" if up < t0 else "token up only after step 0 began") + (
        f", gone {len(drops)} times during the run" if drops else ", held to the done clock")


@judges("C3", "clean")
def c3(kit: Kit) -> Judgement:
    ev = _ev(kit, "clean")
    if 0 not in ev.clocks:
        return False, "step 0 never came"
    t0 = ev.clocks[0][0]
    pri = [(k, t) for k, t in ev.priors() if t <= t0]
    if not pri:
        return False, "no estimate with phase \"prior\" on est/<i> before step 0's clock (the world waits for one from every agent)"
    k, t = pri[0]
    up = next((t for a, t in ev.token_events() if a), t)
    return True, f"prior estimate (k = {k}) {(t - up) / 1e9:.2f} s after its token, {(t0 - t) / 1e9:.2f} s before step 0's clock"


@judges("C4", "clean")
def c4(kit: Kit) -> Judgement:
    ev = _ev(kit, "clean")
    others = {k: v for k, v in ev.from_me.items() if k not in ev.own_keys}
    refused_other = [(k, e) for k, e in ev.refused if kit.name in e and k not in ev.own_keys]
    mine = ", ".join(f"{k.split('/', 2)[2]} ×{v}" for k, v in sorted(ev.from_me.items()))
    if others or refused_other:
        bad = sorted({*others, *(k for k, _e in refused_other)})
        return False, f"messages from {kit.name} on keys not its own: {', '.join(b.split('/', 2)[2] for b in bad)}"
    return True, f"its messages: {mine or 'none'}; none on other keys"


@judges("C5", "clean")
def c5(kit: Kit) -> Judgement:
    ev = _ev(kit, "clean")
    if (why := _complete(kit, ev)) is not None:
        return False, why
    ks = _live_steps(kit, ev)
    miss = {w: [k for k in ks if k not in d] for w, d in (("meas", ev.meas), ("est", {k: 1 for k in ks if ev.posterior(k)}),
                                                         ("health", ev.health))}
    order = []
    for k in ks:
        if k in ev.meas and ev.posterior(k) is not None and k in ev.health:
            tm, te, th = ev.meas[k][0][1], ev.posterior_ns(k), ev.health[k][0][1]
            if te is None or not tm <= te <= th:
                order.append(k)
    dup = sum(len(v) - 1 for d in (ev.meas, ev.health) for v in d.values())
    i = kit.sat
    if any(miss.values()) or order or len(ks) != kit.K:
        parts = [f"{w}/{i} missing at steps {_ranges(v)}" for w, v in miss.items() if v]
        if order:
            parts.append(f"not meas, est, health in that order at steps {_ranges(order)}")
        if len(ks) != kit.K:
            parts.append(f"listed live at {len(ks)}/{kit.K} steps")
        return False, "; ".join(parts)
    return True, (f"meas/{i}, est/{i} (posterior), health/{i} at {len(ks)}/{kit.K} steps, in that order"
                  + (f" ({dup} sent twice)" if dup else ""))


@judges("C6", "clean")
def c6(kit: Kit) -> Judgement:
    run, ev = kit.runs["clean"], _ev(kit, "clean")
    assert run.sc is not None
    timeout = run.sc.emulator.step_timeout_s
    ks = ev.steps()
    late = []
    for a, b in zip(ks, [*ks[1:], None]):
        nxt = ev.clocks[b][0] if b is not None else ev.done_clock_ns
        te = ev.posterior_ns(a)
        if te is None or (nxt is not None and te > nxt):
            late.append(a)
    k_slow, slow = _slowest(ev)
    waited = _world_timeouts(run, kit.sat)
    ok = not late and not waited and slow < 0.8 * timeout
    text = (f"its estimate before the next clock at {len(ks) - len(late)}/{len(ks)} steps; slowest step {slow:.2f} s "
            f"(step {k_slow}; timeout {timeout:g} s)")
    if waited:
        text += f"; the world gave up waiting for it at steps {_ranges(waited)}"
    return ok, text


@judges("C7", "clean")
def c7(kit: Kit) -> Judgement:
    ev = _ev(kit, "clean")
    bad = [(k, e) for k, e in ev.refused if k in ev.own_keys]
    world_mal, world_km = ev.clock_refused
    sent = sum(v for k, v in ev.from_me.items() if k in ev.own_keys)
    if bad:
        k, e = bad[0]
        return False, f"{len(bad)} of its messages refused by the recorder, e.g. on {k.split('/', 2)[2]}: {e[:200]}"
    if world_mal:
        return False, f"the world refused {world_mal} messages ({world_km} key mismatches) in a run where only {kit.name} is new"
    return True, f"all {sent} of its messages pass decode + check_key; the world refused none"


@judges("C8", "clean")
def c8(kit: Kit) -> Judgement:
    run, ev = kit.runs["clean"], _ev(kit, "clean")
    last = max((k for k in ev.est if ev.posterior(k) is not None), default=-1)
    if ev.done_clock_ns is None:
        return False, "the run never ended (no done clock)"
    if run.left_by_itself_s is None:
        return False, f"still running {run.sc.emulator.shutdown_linger_s + 10 if run.sc else 0:g} s after the world ended; " \
                      f"stopped by the supervisor ({_code(run.agent_code)})"
    ok = run.agent_code == 0 and last == kit.K - 1
    return ok, f"left {run.left_by_itself_s:.1f} s after the world ended, {_code(run.agent_code)}; last estimate of step {last}"


@judges("C9", "faults")
def c9(kit: Kit) -> Judgement:
    ev, j = _ev(kit, "faults"), kit.peer
    rep = [f for f, _t in ev.fault_reports("drop", sender=f"agent-{j}")]
    if not rep:
        raise Inconclusive(f"peer {j} never reported its drop fault")
    first = int(rep[0].k)
    gone = [k for k in sorted(ev.batches) if k >= first and j not in ev.batches[k]]
    if not gone:
        raise Inconclusive(f"no batch of peer {j} went missing")
    if (why := _complete(kit, ev)) is not None:
        return False, why
    # Its own drop fault (case faults, later) loses some of its estimates: those steps
    # count when its health report came (the world ends a step on it).
    own = kit.runs["faults"].sc
    assert own is not None
    mine = [(f.k, f.rate) for f, _t in ev.fault_reports("drop", sender=kit.name)]
    f_i, r_i = mine[0] if mine else (kit.K, 0.0)
    no_est = [k for k in gone if ev.posterior(k) is None
              and not (k >= f_i and message_dropped(own.seed, kit.sat, k, DROP_ESTIMATE, r_i) and k in ev.health)]
    listed = sum(1 for k in gone if (e := ev.posterior(k)) is not None and j in e.batches_missing)
    ok = not no_est
    return ok, (f"peer {j}'s batch missing from {len(gone)} steps ({_ranges(gone)}); estimates at "
                f"{len(gone) - len(no_est)}/{len(gone)} of them" + (f" (missing: {_ranges(no_est)})" if no_est else "")
                + f"; listed in est.batches_missing at {listed}")


@judges("C10", "links")
def c10(kit: Kit) -> Judgement:
    run, ev = kit.runs["links"], _ev(kit, "links")
    assert run.sc is not None
    late = sum(1 for ds in ev.rx.values() for d in ds for it in d.items if it.batch.k < d.k)
    if not late and not ev.link_lost_to_me:
        raise Inconclusive("no batch came late or was lost")
    if (why := _complete(kit, ev)) is not None:
        return False, why
    ks = _live_steps(kit, ev)
    no_est = [k for k in ks if ev.posterior(k) is None]
    waited = _world_timeouts(run, kit.sat)
    _k, slow = _slowest(ev)
    ok = not no_est and not waited and len(ks) == kit.K and slow < 0.8 * run.sc.emulator.step_timeout_s
    return ok, (f"deliveries on rx/{kit.sat} at {len(ev.rx)} steps: {late} peer batches late, {ev.link_lost_to_me} lost; "
                f"estimates at {len(ks) - len(no_est)}/{kit.K} steps; slowest step {slow:.2f} s"
                + (f"; the world waited for it at {_ranges(waited)}" if waited else ""))


@judges("C11", "faults", "clean")
def c11(kit: Kit) -> Judgement:
    ev, ref = _ev(kit, "faults"), _ev(kit, "clean")
    off = range(kit.cam_off, kit.cam_on)
    on = range(kit.cam_on, kit.drop_self)

    def rows(e: Evidence, ks) -> int:
        return sum(len(e.meas[k][0][0].target) for k in ks if k in e.meas)

    if rows(ref, off) == 0:
        raise Inconclusive(f"the clean run had no measurement of satellite {kit.sat} at steps {off.start}-{off.stop - 1}")
    if (why := _complete(kit, ev)) is not None:
        return False, why
    r_off, r_on = rows(ev, off), rows(ev, on)
    no_est = [k for k in off if ev.posterior(k) is None]
    no_meas = [k for k in off if k not in ev.meas]
    flagged = sum(1 for k in off if k in ev.health and not any(ev.health[k][0][0].camera_ok))
    ok = r_off == 0 and not no_est and not no_meas and (r_on > 0 or rows(ref, on) == 0)
    return ok, (f"all 6 cameras off at steps {off.start}-{off.stop - 1}: {r_off} measurements (clean run: {rows(ref, off)}), "
                f"batches at {len(off) - len(no_meas)}/{len(off)}, estimates at {len(off) - len(no_est)}/{len(off)}; "
                f"back on: {r_on} measurements at steps {on.start}-{on.stop - 1}; health says cameras off at {flagged}/{len(off)}")


@judges("C12", "faults")
def c12(kit: Kit) -> Judgement:
    run, ev, i = kit.runs["faults"], _ev(kit, "faults"), kit.sat
    assert run.sc is not None
    rep = [(f, t) for f, t in ev.fault_reports("drop", sender=kit.name) if f.HasField("target") and f.target == i]
    if not rep:
        return False, f"no drop report on fault/{kit.name} (phase done, naming the first step it applies to)"
    f = rep[0][0]
    first, rate, seed = int(f.k), float(f.rate), run.sc.seed
    if (why := _complete(kit, ev)) is not None:
        return False, why
    problems = []
    if first != kit.drop_self:
        problems.append(f"its report names step {first}; the command came before step {kit.drop_self}'s batch")
    if abs(rate - 0.5) > 1e-12:
        problems.append(f"its report says rate {rate}, the command 0.5")
    lost_b = [k for k in range(first, kit.K) if message_dropped(seed, i, k, DROP_BATCH, rate)]
    lost_e = [k for k in range(first, kit.K) if message_dropped(seed, i, k, DROP_ESTIMATE, rate)]
    got_b = [k for k in range(kit.K) if k not in ev.meas]
    got_e = [k for k in range(kit.K) if ev.posterior(k) is None]
    if got_b != lost_b:
        problems.append(f"batches missing at {_ranges(got_b)}, the draws say {_ranges(lost_b)}")
    if got_e != lost_e:
        problems.append(f"estimates missing at {_ranges(got_e)}, the draws say {_ranges(lost_e)}")
    no_health = [k for k in range(kit.K) if k not in ev.health]
    if no_health:
        problems.append(f"no health report at {_ranges(no_health)} (the world ends a step on it when the estimate is lost)")
    k_slow, slow = _slowest(ev)
    if slow >= 0.8 * run.sc.emulator.step_timeout_s:
        problems.append(f"step {k_slow} took {slow:.1f} s: the world waited for what was lost")
    if problems:
        return False, "; ".join(problems)
    return True, (f"report names step {first}, rate {rate:g}; batches lost at {_ranges(lost_b)} and estimates at "
                  f"{_ranges(lost_e)}, as drawn; health at {kit.K}/{kit.K} steps; slowest step {slow:.2f} s")


def token_gone_and_back(events: list[tuple[bool, int]], t_kill_cmd: int, t_started: int) -> tuple[bool, list[int]]:
    """Whether the agent's token went between the kill command (less 1 s) and the
    supervisor's report that it started the new process, and the times (ns, the recorder's)
    the token came up after it went: the new process's. Not "after the supervisor's report":
    the recorder hears that report and the new token by different paths, and a program that
    starts quickly declares its token first (a Rust agent's came 0.3 ms before the report
    and was judged never back; CI, 2026-12-05)."""
    went = [t for a, t in events if not a and t_kill_cmd - 1_000_000_000 <= t <= t_started]
    if not went:
        return False, [t for a, t in events if a and t >= t_started]
    return True, [t for a, t in events if a and t > went[0]]


def _commanded_at(ev, action: str, done: int) -> int:
    """When ``action`` was commanded (the world's command; else ``done``, the supervisor's
    report that it carried it out): what the agent does after a kill or restart is counted
    from there (see token_gone_and_back)."""
    cmd = ev.fault_commands(action)
    return cmd[0][1] if cmd else done


@judges("C13", "restart")
def c13(kit: Kit) -> Judgement:
    run, ev = kit.runs["restart"], _ev(kit, "restart")
    kill = ev.fault_reports("kill-agent", sender="supervisor")
    back = ev.fault_reports("restart-agent", sender="supervisor")
    if not kill or not back:
        raise Inconclusive(f"the supervisor reported kill {len(kill)}, restart {len(back)}")
    t_kill, t_back = kill[0][1], back[0][1]
    t_cmd = _commanded_at(ev, "kill-agent", t_kill)
    t_again = _commanded_at(ev, "restart-agent", t_back)
    gone, ups = token_gone_and_back(ev.token_events(), t_cmd, t_back)
    problems = []
    if not gone:
        problems.append("its token did not go after the SIGKILL: the agent outlived it (kill-agent kills the process group "
                        "the supervisor started; a program that leaves it survives)")
    if not ups:
        problems.append("its token never came back after the restart")
    if run.survivors:
        problems.append(f"processes of satellite {kit.sat} still running after the run: {run.survivors}")
    if (why := _complete(kit, ev)) is not None:
        problems.append(why)
    if run.agent_code != 0:
        problems.append(f"the restarted agent ended with {_code(run.agent_code)}")
    after = [k for k in range(kit.restart_at, kit.K) if k in ev.clocks and kit.sat in ev.clocks[k][1]]
    no_health = [k for k in after if k not in ev.health]
    if no_health:
        problems.append(f"listed live but no health at {_ranges(no_health)}")
    if problems:
        return False, "; ".join(problems)
    up_s = max(0.0, (ups[0] - t_again) / 1e9)
    est_after = sum(1 for k in range(kit.restart_at, kit.K) if ev.posterior(k) is not None)
    if est_after == 0 and not any(kit.sat in ev.clocks[k][1] for k in after):
        # docs/agent-contract.md, "Known deviations": the world readmits a restarted agent
        # only once it has published an estimate, which a cold start cannot before sensors.
        est_after_note = " (the world never listed it live again: no cold rejoin, see the contract's known deviations)"
    else:
        est_after_note = ""
    return True, (f"killed at step {kit.kill_at} (token gone), restarted at step "
                  f"{kit.restart_at}: token back {up_s:.1f} s after the restart command; estimates at "
                  f"{est_after}/{kit.K - kit.restart_at} steps after{est_after_note}; {_code(run.agent_code)}; nothing of the killed process left")


@judges("C14", "inputs", "clean")
def c14(kit: Kit) -> Judgement:
    return _inputs(kit, forged=False)


@judges("C15", "inputs", "clean")
def c15(kit: Kit) -> Judgement:
    return _inputs(kit, forged=True)


def _inputs(kit: Kit, forged: bool) -> Judgement:
    run, ev = kit.runs["inputs"], _ev(kit, "inputs")
    inj = run.notes.get("inject") or {}
    if "at_k" not in inj:
        raise Inconclusive(inj.get("error") or run.notes.get("driver_error") or "the kit put nothing")
    if inj["at_k"] > kit.K - 3:
        raise Inconclusive(f"the run was at step {inj['at_k']} of {kit.K - 1} before the kit could put its messages")
    n = inj["forged"] if forged else inj["malformed"]
    kind = "forged" if forged else "malformed"
    same, diff = _same_numbers(kit, ev)
    problems = []
    if run.agent_code != 0 or run.left_by_itself_s is None:
        problems.append(f"it did not live to the end ({_code(run.agent_code)})")
    if diff:
        problems.append(f"numbers differ from the clean run at steps {_ranges(diff)}")
    if forged:
        dropping = [k for k, hs in ev.health.items() if any(h.drop_rate for h, _t in hs)]
        if dropping:
            problems.append(f"it obeyed the forged drop command (drop_rate > 0 at steps {_ranges(dropping)})")
    text = f"{n} {kind} messages put at step {inj['at_k']}"
    if problems:
        return False, text + ": " + "; ".join(problems)
    return True, text + f": alive to the end ({_code(run.agent_code)}), its estimates and batches equal the clean run's bit for bit at {len(same)}/{kit.K} steps"


@judges("C16", "inputs", "clean")
def c16(kit: Kit) -> Judgement:
    run, ev, ref = kit.runs["inputs"], _ev(kit, "inputs"), _ev(kit, "clean")
    inj = run.notes.get("inject") or {}
    if "at_k" not in inj:
        raise Inconclusive(inj.get("error") or run.notes.get("driver_error") or "the kit put nothing")
    h, h0 = ev.last_health(), ref.last_health()
    if h is None:
        return False, "no health report"
    base_m, base_k = (h0.malformed, h0.key_mismatch) if h0 is not None else (0, 0)
    dm, dk = int(h.malformed) - int(base_m), int(h.key_mismatch) - int(base_k)
    need_m, need_k = inj["malformed"] + inj["forged"], inj["forged"]
    ok = dm >= need_m and dk >= need_k
    return ok, (f"its last health report counts {dm} malformed (of them {dk} key mismatches) more than the clean run's; "
                f"the kit put {need_m} ({need_k} forged)")


@judges("C17", "router", "clean")
def c17(kit: Kit) -> Judgement:
    run, ev = kit.runs["router"], _ev(kit, "router")
    rep = ev.fault_reports("restart-router", sender="supervisor") or [(f, 0) for f in run.router_faults if f.get("phase") == "done"]
    if not rep:
        raise Inconclusive("the router was not restarted (no supervisor report)")
    gap = ev.gaps[0] if ev.gaps else None
    if (why := _complete(kit, ev)) is not None:
        return False, why
    same, diff = _same_numbers(kit, ev)
    problems = []
    if diff:
        problems.append(f"numbers differ from the clean run (or are missing) at steps {_ranges(diff)}")
    if run.agent_code != 0:
        problems.append(f"it ended with {_code(run.agent_code)}")
    g = f"a {(gap.up_unix_ns - gap.down_unix_ns) / 1e9:.1f} s bus gap after step {gap.last_step_before}" if gap and gap.up_unix_ns \
        else "the router restarted at step " + str(kit.mid)
    if problems:
        return False, f"{g}: " + "; ".join(problems)
    return True, f"{g}: estimates and batches equal the clean run's bit for bit at {len(same)}/{kit.K} steps; {_code(run.agent_code)}"


@judges("C18", "bus-lost")
def c18(kit: Kit) -> Judgement:
    run = kit.runs["bus-lost"]
    assert run.sc is not None
    bound = run.sc.emulator.bus_lost_after_s
    down = next((f.get("t_down_unix_s") for f in run.router_faults if f.get("action") == "kill-router"), None)
    if down is None:
        raise Inconclusive("the router was not killed")
    if run.agent_ended_at is None:
        return False, f"still running after the bus was gone ({_code(run.agent_code)} once stopped)"
    after = run.agent_ended_at - down
    ok = run.agent_code == 3 and bound - 0.5 <= after <= bound + 15.0
    return ok, f"{_code(run.agent_code)} {after:.1f} s after the router was killed (emulator.bus_lost_after_s: {bound:g} s)"


@judges("C19", "world-gone")
def c19(kit: Kit) -> Judgement:
    run = kit.runs["world-gone"]
    w = run.notes.get("world_killed") or {}
    if "t" not in w:
        raise Inconclusive(w.get("error") or run.notes.get("driver_error") or "the world was not killed")
    if run.agent_ended_at is None:
        return False, f"still running after the world was gone ({_code(run.agent_code)} once stopped)"
    assert run.sc is not None
    hold = run.sc.emulator.bus_lost_after_s  # a world's token may be held this long (it may only be stalled)
    after = run.agent_ended_at - w["t"]
    ok = run.agent_code == 4 and after <= hold + 10.0
    return ok, (f"world SIGKILLed at step {w['at_k']}: {_code(run.agent_code)} {after:.1f} s later "
                f"(at most emulator.bus_lost_after_s {hold:g} s + 10 s)")


@judges("C20", "sigterm")
def c20(kit: Kit) -> Judgement:
    run, ev = kit.runs["sigterm"], _ev(kit, "sigterm")
    cmd = ev.fault_commands("stop-agent")
    rep = ev.fault_reports("stop-agent", sender="supervisor")
    if not cmd or not rep:
        raise Inconclusive(f"stop-agent: command {len(cmd)}, supervisor report {len(rep)}")
    took = (rep[0][1] - cmd[0][1]) / 1e9
    gone = [t for a, t in ev.token_events() if not a and t >= cmd[0][1]]
    problems = []
    if run.agent_codes and run.agent_codes[0] != 0:
        problems.append(f"{_code(run.agent_codes[0])}")
    if took > 5.0:
        problems.append(f"it took {took:.1f} s (more than 5 s)")
    if not gone:
        problems.append("its token did not go")
    if run.survivors:
        problems.append(f"left processes behind: {run.survivors}")
    if problems:
        return False, "SIGTERM at step " + str(kit.mid) + ": " + "; ".join(problems)
    return True, f"SIGTERM at step {kit.mid}: exit 0 within {took:.1f} s, token gone, nothing left in its process group"


@judges("C21", "clean", "restart")
def c21(kit: Kit) -> Judgement:
    cov = kit.runs["clean"].notes.get("cov") or {}
    ev = _ev(kit, "restart")
    problems = []
    if "error" in cov or "k" not in cov:
        problems.append(f"cov/{kit.sat}: {cov.get('error') or kit.runs['clean'].notes.get('driver_error') or 'not asked'}")
    else:
        if cov["own"] != kit.sat or cov["rows"] < 1:
            problems.append(f"cov/{kit.sat} answered for satellite {cov['own']} with {cov['rows']} rows")
        if not cov["asked_at_k"] - 1 <= cov["k"] <= cov["asked_at_k"] + 1:
            problems.append(f"cov/{kit.sat} served step {cov['k']} when the run was at step {cov['asked_at_k']}")
    back = ev.fault_reports("restart-agent", sender="supervisor")
    if not back:
        raise Inconclusive("no restart")
    # The killed process is dead by the restart command, so a prior after it is the new one's.
    t_from = _commanded_at(ev, "restart-agent", back[0][1])
    c0 = ev.clocks.get(kit.restart_at)
    pri = [(k, t) for k, t in ev.priors() if t >= t_from and (c0 is None or t <= c0[0])]
    if not pri:
        problems.append(f"no prior estimate after the restart before step {kit.restart_at}'s clock")
    elif pri[0][0] < kit.restart_at - 1:
        problems.append(f"restarted at step {pri[0][0]}, not at the swarm's present ({kit.restart_at - 1}): not warm")
    no_est = [k for k in range(kit.restart_at, kit.K) if ev.posterior(k) is None]
    if no_est:
        problems.append(f"no estimate after the restart at steps {_ranges(no_est)}")
    if problems:
        return False, "; ".join(problems)
    return True, (f"cov/{kit.sat} served step {cov['k']} ({cov['rows']} satellites) in {cov['ms']:.0f} ms; restarted, its prior "
                  f"is of step {pri[0][0]} (the swarm's present) and it estimated every step after")


@judges("C22", "links")
def c22(kit: Kit) -> Judgement:
    run, ev = kit.runs["links"], _ev(kit, "links")
    ests = [ev.posterior(k) for k in range(kit.K) if ev.posterior(k) is not None]
    used = sum(e.late_used for e in ests)
    replayed = sum(e.replayed_steps for e in ests)
    dropped = sum(e.late_dropped for e in ests)
    late = sum(1 for ds in ev.rx.values() for d in ds for it in d.items if it.batch.k < d.k)
    if not late:
        raise Inconclusive("no batch came late")
    assert run.sc is not None
    ok = used > 0 and replayed > 0
    return ok, (f"{late} late peer batches delivered; its estimates report {used} late measurements used, {replayed} steps "
                f"replayed, {dropped} dropped (filter.late: {run.sc.filter.late})")
