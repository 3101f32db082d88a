"""A lost last reply and the bulk request's order: the BEAR legs' bulk cycle (`bruce_hw.bear_legs.BearLegs`) against
the driver's BEAR emulator on a pseudo-terminal, on the wall clock, one cycle a millisecond, with each reply dropped
at random (`--drop`, default 5 %: the rare runs of 1 % come often enough to count).

The BEARs answer in request order and the driver ends a cycle once the last ID has answered; a lost reply before the
last is known lost at once, but a lost last reply is waited for up to the reply gap (`drivers.bear.REPLY_GAP_S`), and
every ID's next sample comes that much later. With the IDs in a fixed order the last ID pays that on each of its own
losses: three in a row aged its sample past `safety.max_sensor_age_s` (8 ms) in a 1-% stand. The shipped order turns
by one ID a cycle. The two are alternated, `--rounds` times `--seconds` each; per order: the cycles, how many cycle
ends found some sample older than 5 and 7 ms (and which IDs), and the oldest.

    python bench/bench_last_reply_order.py [--seconds 20] [--rounds 2] [--drop 0.05]
"""

from __future__ import annotations

import argparse
import time
from collections import Counter

import numpy as np

from bruce_hw.bear_legs import BearLegs
from bruce_hw.config import load_config
from drivers.emulators.bear import BearBusEmulator

IDS = list(range(1, 11))
OLD_S = (0.005, 0.007)


def run(order: str, seconds: float, drop: float, seed: int) -> dict:
    with BearBusEmulator(IDS) as emulator:
        config = load_config(overrides=[f"buses.bear.port={emulator.path}"])
        legs = BearLegs(config, ping_rounds=3, ping_retry_s=0.01, clear_attempts=2,
                        reply_timeout_s=config.buses.bear.reply_timeout_s, turn_order=order != "fixed")
        legs.open()
        try:
            legs.cycle(None, retry=True)
            emulator.set_reply_loss(drop, 0.0, seed)
            old = {limit: Counter() for limit in OLD_S}
            oldest, cycles = 0.0, 0
            start = deadline = time.monotonic()
            while time.monotonic() - start < seconds:
                reading = legs.cycle(None)
                ages = time.monotonic() - reading.stamps
                k = int(np.argmax(ages))
                oldest = max(oldest, float(ages[k]))
                for limit in OLD_S:
                    if ages[k] > limit:
                        old[limit][IDS[k]] += 1
                cycles += 1
                deadline = max(deadline + 0.001, time.monotonic() - 0.001)
                time.sleep(max(0.0, deadline - time.monotonic()))
            return {"cycles": cycles, "old": old, "oldest": oldest, "lost": int(legs.loss.total.sum())}
        finally:
            legs.close()


def by_id(counts: Counter) -> str:
    return ", ".join(f"ID {i}: {n}" for i, n in sorted(counts.items())) or "-"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--seconds", type=float, default=20.0)
    parser.add_argument("--rounds", type=int, default=2)
    parser.add_argument("--drop", type=float, default=0.05)
    args = parser.parse_args()
    print(f"{args.seconds:g} s per run, replies dropped at {100 * args.drop:g} %, orders alternated {args.rounds} "
          f"rounds")
    for r in range(args.rounds):
        for order in ("fixed", "turning"):
            got = run(order, args.seconds, args.drop, seed=r)
            worst = ", ".join(f"> {1e3 * limit:g} ms: {sum(c.values())} ({by_id(c)})"
                              for limit, c in got["old"].items())
            print(f"round {r + 1} {order:7s}: {got['cycles']} cycles, {got['lost']} replies lost; cycle ends with a "
                  f"sample older than {worst}; oldest {1e3 * got['oldest']:.1f} ms", flush=True)


if __name__ == "__main__":
    main()
