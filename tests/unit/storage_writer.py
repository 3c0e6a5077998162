"""Child process of the storage crash test: append until killed.

Usage: ``python storage_writer.py DIRECTORY``. In a fresh store, record ``k``
has seq ``k``, op ``{"k": k}`` and a 32 KiB array full of ``k``; appends carry
1 to 3 records (group commit). After each append returns, its last seq is
printed and flushed: that line is the acknowledgement. Every 50 appends a
snapshot with meta ``{"k": seq}`` and ``arrays["ks"] = 1..seq`` is written.
"""

from __future__ import annotations

import itertools
import sys
from pathlib import Path

import numpy as np

from services.embedding.storage import CacheStore, Record

VECTOR_LEN = 4096


def record(k: int) -> Record:
    return Record(op={"k": k}, arrays={"v": np.full(VECTOR_LEN, k, dtype=np.int64)})


def main(directory: Path) -> None:
    with CacheStore(directory) as store:
        store.load()
        seq = 0
        for n in itertools.count(1):
            seq = store.append([record(seq + i) for i in range(1, n % 3 + 2)])
            print(seq, flush=True)
            if n % 50 == 0:
                store.write_snapshot({"k": seq}, {"ks": np.arange(1, seq + 1)})


if __name__ == "__main__":
    main(Path(sys.argv[1]))
