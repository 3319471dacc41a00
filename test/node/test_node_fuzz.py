"""The node over real Fast DDS, fed 2,000 seeded fuzz messages (valid and invalid, mixed).

Every valid message must be answered exactly once with the expected segment ids, no invalid
one answered, and every /diagnostics report must satisfy
`received = answered + dropped + rejected + failed + in_flight`. Needs no shared data (the
bank is synthetic). `make fuzz` runs 10,000 (point_gn_ros/clients/fuzz.py).
"""

from __future__ import annotations

import json

from node_testing import DOMAIN_ID

from point_gn_ros.clients.fuzz import run_fuzz

COUNT = 2000


def test_fuzz_2000_messages_over_dds() -> None:
    report = run_fuzz(COUNT, seed=2026, window=8, domain_id=DOMAIN_ID)
    summary = json.dumps({k: v for k, v in report.items() if k != 'kinds'}, indent=1)
    assert report['ok'], summary
    assert report['sent'] == COUNT and report['valid'] > COUNT // 2 > report['invalid'] > 0
    assert report['lost_valid'] == 0 and report['duplicates'] == 0
    assert report['identity_violations'] == 0 and report['reports'] >= 3
    final = report['final_diagnostics']
    assert int(final['rejected']) == report['invalid'] and int(final['failed']) == 0
    # Every invalid kind of the generator was sent and rejected under a named reason.
    assert len([k for k in final if k.startswith('rejected.')]) >= 8
