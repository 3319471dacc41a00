"""Bank rows appended in place (bank/store.py): no version ever sees its rows change."""

from __future__ import annotations

import threading

import torch

from point_gn_ros.bank.store import append_rows, with_room


def test_append_shares_one_buffer_and_keeps_every_version() -> None:
    base = torch.randn(100, 8)
    v1 = append_rows(base, torch.randn(3, 8))
    v2 = append_rows(v1, torch.randn(2, 8))
    assert torch.equal(v1[:100], base) and v2.shape == (105, 8) and v2.is_contiguous()
    assert v2.data_ptr() == v1.data_ptr()                     # in place: no copy of v1
    snap1, snap2 = v1.clone(), v2.clone()
    # v1 appended to again (a branch): v2's rows must not be overwritten -> a new buffer
    v2b = append_rows(v1, torch.ones(2, 8))
    assert v2b.data_ptr() != v1.data_ptr()
    assert torch.equal(v2, snap2) and torch.equal(v1, snap1)
    assert torch.equal(v2b, torch.cat([snap1, torch.ones(2, 8)]))
    # the latest version keeps appending in place, past its buffer's room into a new one
    v = v2
    for _ in range(200):
        v = append_rows(v, torch.full((3, 8), 7.0))
    assert v.shape == (705, 8) and torch.equal(v[:105], snap2) and (v[105:] == 7).all()
    assert torch.equal(append_rows(base[::2], torch.zeros(1, 8)),
                       torch.cat([base[::2], torch.zeros(1, 8)]))


def test_concurrent_appends_to_one_version_never_share_rows() -> None:
    v1 = append_rows(torch.zeros(10, 4), torch.zeros(1, 4))
    out: list[torch.Tensor] = [torch.empty(0)] * 8

    def add(i: int) -> None:
        out[i] = append_rows(v1, torch.full((5, 4), float(i + 1)))

    threads = [threading.Thread(target=add, args=(i,)) for i in range(8)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    for i, v in enumerate(out):
        assert (v[11:] == i + 1).all() and (v[:11] == 0).all()


def test_rows_with_room_take_the_first_append_in_place() -> None:
    base = torch.randn(50, 6)
    roomy = with_room(base)
    assert torch.equal(roomy, base) and roomy.data_ptr() != base.data_ptr()
    assert with_room(roomy) is roomy
    assert append_rows(roomy, torch.randn(4, 6)).data_ptr() == roomy.data_ptr()
