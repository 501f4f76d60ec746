"""Which faults go where: the seeded plan of bursts over the epochs of the drive.

Structured cases are played in shuffled rounds (every case once per round, heavy cases in
the first round only) until the asked number of messages is reached; the first round plays
every case, with fewer copies each when the count is small. Each topic also gets one flood
(three times its subscription depth of valid messages at once). Random mutations come in
bursts of one operator on one topic. All bursts are shuffled together and spread evenly
over the epochs between the warm-up and the clean tail. With ``prestart``, a negative stamp
is sent on each stamped sensor topic and link before the first valid message (the issue's
"negative stamp on the first epoch").
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from msg_adapters import wire

from . import cases as fault_cases
from .mutate import OPERATORS, MutationKind

#: Weights of the mutation operators: the message-level ones (that reach a callback) more
#: often than the CDR-level ones.
OPERATOR_WEIGHTS = {'bit_flip': 3, 'field_swap': 2, 'scale': 3, 'truncate': 2,
                    'cdr_bit_flip': 1, 'cdr_truncate': 1, 'cdr_garbage': 1}
MUTATION_BURST = 5
PRESTART_TOPICS = (wire.GNSS, wire.TWIST, wire.IMU, wire.GNSS_MEASUREMENTS)


@dataclass(frozen=True)
class Burst:
    """``n`` messages of one kind (a :class:`.cases.Case` or a :class:`.mutate.MutationKind`)
    before the GNSS epoch of index ``slot`` (-1: before the first valid message)."""

    fault: object
    n: int
    slot: int

    @property
    def kind(self) -> str:
        return self.fault.kind


def prestart_cases() -> list:
    """A negative stamp on each stamped topic, before anything valid arrived."""
    out = []
    for topic in PRESTART_TOPICS:
        case = next(c for c in fault_cases.stamp_cases(topic) if c.name == 'stamp_negative')
        out.append(fault_cases.Case(topic, 'stamp_negative_first', case.build, issue=True,
                                    burst=1))
    return out


def plan(cases: list, topics: tuple[str, ...], structured: int, mutations: int,
         slots: list[int], rng: np.random.Generator, burst: int = 10,
         prestart: bool = True) -> list[Burst]:
    """The bursts of a run.

    Args:
        cases: The structured cases to play (heavy ones included or not).
        topics: Topics the mutations go to.
        structured: Structured messages to send (at least one round is played when
            ``structured`` > 0, cut short when the count is reached).
        mutations: Mutated messages to send.
        slots: Epoch indices the bursts may go before (the fault window).
        rng: Random generator (the run's seed).
        burst: Most messages per burst.
        prestart: Add the negative stamps before the first valid message.
    """
    bursts: list[tuple[object, int]] = []
    floods = [c for c in cases if c.family == 'flood']
    cases = [c for c in cases if c.family != 'flood']
    # The first round plays every case (fewer copies each when the count is small), the
    # next ones full bursts until the count is reached.
    left, first = structured, True
    share = max(1, structured // max(len(cases), 1))
    while left > 0 and cases:
        for i in rng.permutation(len(cases)):
            case = cases[int(i)]
            if left <= 0:
                break
            if case.heavy and not first:
                continue
            n = 1 if case.heavy else min(case.size, burst, share if first else left)
            bursts.append((case, n))
            left -= n
        first = False
        if all(c.heavy for c in cases):
            break
    bursts += [(c, c.size) for c in floods if structured > 0]
    names = list(OPERATOR_WEIGHTS)
    weights = np.array([OPERATOR_WEIGHTS[o] for o in names], dtype=float)
    assert set(names) == set(OPERATORS)
    left = mutations
    while left > 0 and topics:
        topic = topics[int(rng.integers(len(topics)))]
        operator = names[int(rng.choice(len(names), p=weights / weights.sum()))]
        n = min(MUTATION_BURST, burst, left, fault_cases.TOPIC_BURST[topic])
        bursts.append((MutationKind(topic, operator), n))
        left -= n
    order = rng.permutation(len(bursts))
    out = []
    if prestart:
        out += [Burst(c, 1, -1) for c in prestart_cases()]
    if bursts and not slots:
        raise ValueError('no epochs to place the faults in: lengthen the drive or shorten '
                         'the warm-up and the tail')
    for j, i in enumerate(order):
        fault, n = bursts[int(i)]
        out.append(Burst(fault, n, slots[j * len(slots) // len(bursts)]))
    return out


def meta(faults) -> dict[str, dict]:
    """kind -> topic, family, expect, issue of every fault kind (of a plan, or all cases)."""
    return {f.kind: {'topic': f.topic, 'family': f.family, 'expect': f.expect,
                     'issue': f.issue} for f in faults}
