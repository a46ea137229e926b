"""Record a leave-family-out run's result in an exported model's card, without exporting again:

    python -m export.leave_family_out --model-dir models/fast-vgqcnn-default runs/fast-v2-lfo/eval/metrics_test.json

The file is a ``python -m training evaluate`` result of a run that never saw some families
(``datagen sample --set sampling.holdout_families=[...]``); its ``held_out_families`` entry (those
families' rows together, and each family's own metrics) becomes the card's
``metrics.leave_family_out``. The card is rewritten atomically; every other key, and every other
file of the model folder, stays as exported. ``python -m export --leave-family-out FILE`` records
the same entry at export time.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from vgq import atomic
from vgq.model_card import CARD_NAME, ModelCard


def _read_result(path: str | Path) -> dict:
    try:
        r = json.loads(Path(path).read_text())
        r["held_out_families"]
    except (OSError, json.JSONDecodeError, KeyError, TypeError) as e:
        raise ValueError(f"{path}: not a `training evaluate` result ({e})") from None
    return r


def _metrics(r: dict, path: str | Path) -> dict:
    held = r["held_out_families"]
    if not held:
        raise ValueError(f"{path}: evaluated on a dataset without held-out families")
    out = {**held, "by_family": {f: r["by_family"][f] for f in held["families"] if f in r.get("by_family", {})}}
    if r.get("samples_seen") is not None:  # which checkpoint of the run: its training samples
        out["samples_seen"] = int(r["samples_seen"])
    return out


def leave_family_out_metrics(path: str | Path) -> dict:
    """The card's ``leave_family_out`` entry from a `training evaluate` result of a leave-family-out
    run (its held-out families' rows together, plus their own metrics under ``by_family`` and the
    checkpoint's ``samples_seen``);
    ValueError naming the file when it is not such a result."""
    return _metrics(_read_result(path), path)


def record(model_dir: str | Path, result: str | Path) -> dict:
    """Write ``result``'s leave-family-out metrics into the card in ``model_dir``; return them.
    ValueError for a folder without a readable card or a result of another architecture."""
    card_path = Path(model_dir) / CARD_NAME
    try:
        d = json.loads(card_path.read_text())  # every other key exactly as exported
        arch = ModelCard.from_dict(d).architecture
    except (OSError, json.JSONDecodeError, KeyError, TypeError, ValueError) as e:
        raise ValueError(f"{model_dir}: no readable model card ({e})") from None
    r = _read_result(result)
    lfo = _metrics(r, result)
    if r.get("arch") not in (None, arch):
        raise ValueError(f"{result}: a {r['arch']} run; the model in {model_dir} is {arch}")
    d.setdefault("metrics", {})["leave_family_out"] = lfo
    atomic.write_json(card_path, d)
    return lfo


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(
        prog="python -m export.leave_family_out",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    ap.add_argument("--model-dir", required=True, help="exported model folder whose card gets the result")
    ap.add_argument("result", help="metrics_test.json of `training evaluate` on the leave-family-out run")
    a = ap.parse_args(argv)
    try:
        m = record(a.model_dir, a.result)
    except ValueError as e:
        print(f"export.leave_family_out: error: {e}", file=sys.stderr)
        return 2
    fams = " + ".join(m["families"])
    print(
        f"{a.model_dir}: leave_family_out ({fams}, never seen) balanced accuracy {100 * m['balanced_accuracy']:.1f}% "
        f"on {m['n']} rows, AUC {m.get('auc', float('nan')):.3f}"
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())
