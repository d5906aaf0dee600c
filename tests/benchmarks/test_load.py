"""A short sustained-load run (scripts/load.py) against a real ``python -m service``: a fixed
rate of alignments with registrations and deletions beside them; no 5xx, nothing lost."""

from __future__ import annotations

import json
import subprocess
import sys

from tests.servers import REPO, needs_model

pytestmark = needs_model

RATE, DURATION_S = 2, 10  # well under what 2 busy cores sustain (scripts/load.py --find-max)


def test_a_short_sustained_load(tmp_path):
    command = [
        sys.executable,
        str(REPO / "scripts" / "load.py"),
        f"--rate={RATE}",
        f"--duration={DURATION_S}",
        "--write-every=2",
        "--keep=3",
        "--json",
    ]
    done = subprocess.run(command, cwd=tmp_path, capture_output=True, text=True, timeout=180)
    print(done.stdout)
    assert done.returncode == 0, done.stdout + done.stderr
    result = json.loads(done.stdout.strip().splitlines()[-1])
    assert result["errors_5xx"] == 0 and result["transport_errors"] == 0
    assert result["align_sent"] == RATE * DURATION_S and result["dropped"] == 0
    assert result["align_ok"] == result["align_sent"]  # gallery objects: every one recognised
    assert result["achieved_rate"] >= 0.8 * RATE
    references = result["references"]
    # one every 2 s; beyond 3, the oldest is read back and deleted
    assert references["registered"] >= 3 and references["deleted"] >= references["registered"] - 4
    assert references["read_back"] == references["registered"]
    assert references["lost"] == references["changed"] == references["resurrected"] == 0
    assert result["rss_mib_start"] > 0 and result["rss_mib_end"] > 0
    assert len(result["rss_samples"]) >= 4  # sampled every 2 s while the load ran
    assert 0 < result["rss_mib_after_warmup"] <= result["rss_mib_peak"]
    assert 0 < result["rss_mib_last_window"] <= result["rss_mib_peak"]
