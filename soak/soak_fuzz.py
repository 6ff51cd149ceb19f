"""Soak: the NDI reply parsers fuzzed with a million inputs (issue 14); 0 unexpected exceptions.

"Unexpected" is what ``src/fullperc_drivers/test/test_ndi_fuzz.py`` says it is: every parser the driver uses
(:func:`test_ndi_fuzz.parse_everything`: the frame reader, status/OKAY checks, BX and TX in every reply option,
PHSR/PHRQ/VER/APIREV/GET, command decoding, ROM reading) may raise only ``NdiError``; anything else escaping
(IndexError, struct.error, UnicodeDecodeError, ValueError, ...) is a bug. The unit test runs a few thousand
hypothesis examples; this runs the same input kinds, drawn by a seeded ``random.Random``, a million times:

* random bytes (0-600);
* real replies (BX/TX in every option, OKAY, ERROR, WARNING, PHSR, VER, GET) with 1-6 mutations (bit flip, byte
  set, insert, delete, truncate);
* the same mutated replies re-framed with a valid CRC, so the damage reaches the payload parsers;
* random binary bodies and random ASCII bodies (the reply alphabet) behind a valid CRC.

Prints (the bench/benchlib.py line format)::

  {"name": "fuzz_inputs", "value": 1000000, "unit": "count"}
  {"name": "fuzz_unexpected_exceptions", "value": 0, "unit": "count", "of": 1000000}
  {"name": "fuzz_inputs_per_s", "value": ..., "unit": "1/s"}

and on stderr the first inputs that raised something else (hex), one per exception type. Exit status 1 if any.

  source scripts/env.sh && python soak/soak_fuzz.py [--inputs 1000000] [--seed 0]
"""

from __future__ import annotations

import argparse
import random
import sys
import time
from collections import Counter
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "bench"))
sys.path.insert(0, str(ROOT / "src" / "fullperc_drivers" / "test"))

from benchlib import emit  # noqa: E402
from test_ndi_fuzz import SEEDS, parse_everything, recrc  # noqa: E402

from fullperc_drivers.ndi.protocol import encode_ascii_reply, encode_binary_reply  # noqa: E402

ASCII_ALPHABET = "0123456789ABCDEF+-MISNGDABLEUOC\n"


def mutate(rng: random.Random, raw: bytes) -> bytes:
    b = bytearray(raw)
    for _ in range(rng.randint(1, 6)):
        if not b:
            break
        i = rng.randrange(len(b))
        op = rng.randrange(5)
        if op == 0:
            b[i] ^= 1 << rng.randrange(8)
        elif op == 1:
            b[i] = rng.randrange(256)
        elif op == 2:
            b[i:i] = rng.randbytes(rng.randint(1, 8))
        elif op == 3:
            del b[i]
        else:
            del b[i:]
    return bytes(b)


def make_input(rng: random.Random, kind: int) -> bytes:
    if kind == 0:
        return rng.randbytes(rng.randrange(601))
    if kind == 1:
        return mutate(rng, rng.choice(SEEDS))
    if kind == 2:
        return recrc(mutate(rng, rng.choice(SEEDS)))
    if kind == 3:
        return encode_binary_reply(rng.randbytes(rng.randrange(301)))
    return encode_ascii_reply("".join(rng.choices(ASCII_ALPHABET, k=rng.randrange(301))))


KINDS = ("random bytes", "mutated replies", "mutated payloads, valid CRC", "random binary bodies, valid CRC",
         "random ASCII bodies, valid CRC")


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--inputs", type=int, default=1_000_000)
    ap.add_argument("--seed", type=int, default=0)
    a = ap.parse_args()
    rng = random.Random(a.seed)
    unexpected: Counter[str] = Counter()
    examples: dict[str, tuple[int, bytes, str]] = {}
    per_kind = Counter()
    t0 = time.perf_counter()
    for n in range(a.inputs):
        kind = n % len(KINDS)
        raw = make_input(rng, kind)
        per_kind[kind] += 1
        try:
            parse_everything(raw)
        except Exception as e:  # noqa: BLE001 - anything but NdiError escaping is what this counts
            name = type(e).__name__
            unexpected[name] += 1
            examples.setdefault(name, (kind, raw, str(e)))
        if n and n % 200_000 == 0:
            print(f"# {n} inputs, {sum(unexpected.values())} unexpected, {time.perf_counter() - t0:.0f} s",
                  file=sys.stderr, flush=True)
    dt = time.perf_counter() - t0
    total = sum(unexpected.values())
    emit("fuzz_inputs", a.inputs, "count", kinds={KINDS[k]: v for k, v in sorted(per_kind.items())}, seed=a.seed)
    emit("fuzz_unexpected_exceptions", total, "count", of=a.inputs, by_type=dict(unexpected))
    emit("fuzz_inputs_per_s", a.inputs / dt, "1/s", seconds=round(dt, 1))
    for name, (kind, raw, msg) in examples.items():
        print(f"{name} ({KINDS[kind]}): {msg}\n  input: {raw.hex()}", file=sys.stderr)
    return 1 if total else 0


if __name__ == "__main__":
    sys.exit(main())
