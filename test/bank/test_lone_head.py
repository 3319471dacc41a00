"""A lone query's compiled head (vote.py CompiledHead, pgn_head.c) against the torch reference."""

from __future__ import annotations

import numpy as np
import torch

from point_gn_ros.bank.classifier import Classifier, GATE_SKIP
from point_gn_ros.bank.discriminant import fit_head
from point_gn_ros.bank.vote import CompiledHead
from point_gn_ros.bank.store import FeatureBank
from point_gn_ros.bank.model import FeatureTransform
from point_gn_ros.clients.node_client import load_demo_objects, place_in_sensor_frame
from point_gn_ros.commands.bench_cmd import synthetic_bank
from point_gn_ros.core.config import EncoderConfig
from point_gn_ros.recognizer import Recognizer

D = EncoderConfig().feature_dim


def _one_by_one(clf: Classifier, feats: torch.Tensor
                ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor | None]:
    out = [clf._evaluate(feats[i:i + 1]) for i in range(len(feats))]
    gate = None if out[0][2] is None else torch.cat([o[2] for o in out])
    return torch.cat([o[0] for o in out]), torch.cat([o[1] for o in out]), gate


def test_the_shipped_bank_answers_a_lone_query_as_a_batch_does() -> None:
    """Both sections (exact int4 scan with the ridge term; index with the wide LDA), the gate."""
    rec = Recognizer.from_bank(None)
    clf = rec.classifier
    assert clf.lone and clf.views.compiled_head is not None and clf.compiled_gate is not None
    assert clf.search._packed is not None  # the complete section's int4 codes, from nibbles
    objects = load_demo_objects()
    rng = np.random.default_rng(5)
    feats = rec.encode([place_in_sensor_frame(x, rng, single_view=view)
                        for view in (False, True) for x in objects.xyz])
    with torch.no_grad():
        prob, novelty, gate = clf._evaluate(feats)          # a batch
    lone_prob, lone_novelty, lone_gate = _one_by_one(clf, feats)
    assert gate is not None and lone_gate is not None
    # every branch ran: one section only, the other only, and both mixed
    assert (gate <= GATE_SKIP).any() and (gate >= 1 - GATE_SKIP).any()
    assert ((gate > GATE_SKIP) & (gate < 1 - GATE_SKIP)).any()
    torch.testing.assert_close(lone_gate, gate, atol=1e-5, rtol=0)
    # the batch embeds in torch, a lone query in C: within float32 rounding
    torch.testing.assert_close(lone_prob, prob, atol=2e-5, rtol=0)
    torch.testing.assert_close(lone_novelty, novelty, atol=1e-6, rtol=0)
    assert torch.equal(lone_prob.argmax(1), prob.argmax(1))
    res = clf.classify(feats[:1])
    assert res.labels[0] == int(prob[0].argmax()) and res.partial is not None


def test_whitened_lda_head_and_absent_class() -> None:
    classes = 6
    feats, labels = synthetic_bank(2_000, 64, seed=1, classes=classes)
    labels = np.where(labels == 5, 4, labels)                # class 5: no entries
    z, y = torch.from_numpy(feats), torch.from_numpy(labels)
    tf = FeatureTransform(torch.zeros(D), torch.ones(D), torch.eye(D)[:, :64].contiguous())
    names = [f'c{i}' for i in range(classes)]
    head = fit_head(z, y, classes, gamma=30.0, alpha=0.3, lda_alpha=0.1, fusion_weight=0.3,
                    temperature=1.5)
    bank = FeatureBank(head.vote_space(z), y, names, EncoderConfig(), tf, 30.0,
                       {'head': {'alpha': 0.3}}, head=head)
    plain = FeatureBank(z, y, names, EncoderConfig(), tf, 30.0)
    rng = np.random.default_rng(2)
    raw = torch.zeros(12, D)
    raw[:, :64] = torch.from_numpy(feats[rng.integers(0, len(feats), 12)]
                                   + rng.normal(0, 0.05, (12, 64)).astype(np.float32))
    for b in (bank, plain):
        clf = Classifier(b)
        assert clf.lone
        if b is bank:
            head = clf.compiled_head
            assert head.lda_coef is not None and head.embed.whiten is not None
        prob, novelty = Classifier(b, compiled=False).evaluate(raw)   # the torch reference
        lone_prob, lone_novelty, gate = _one_by_one(clf, raw)
        assert gate is None
        assert (lone_prob[:, 5] == 0).all() and (prob[:, 5] == 0).all()
        torch.testing.assert_close(lone_prob, prob, atol=2e-6, rtol=0)
        torch.testing.assert_close(lone_novelty, novelty, atol=1e-6, rtol=0)


def test_what_the_compiled_path_does_not_cover_keeps_the_torch_path() -> None:
    """A ridge head whose coefficients are not float32 values (a float64 refit)."""
    bank = FeatureBank.load(None)
    clf = Classifier(bank)
    clf.head.ridge_coef = clf.head.ridge_coef + 1e-12      # no longer float32 values
    assert CompiledHead.build(clf.transform, clf.head, bank.num_classes, clf.search) is None
    clf = Classifier(bank)
    assert CompiledHead.build(clf.transform, clf.head, bank.num_classes, clf.search) is not None


def test_a_batch_is_finished_in_compiled_code_as_the_torch_head_finishes_it() -> None:
    """The shipped bank's exact section: batch rows after the scan through pgn_head_finish."""
    rec = Recognizer.from_bank(None)
    clf = Classifier(rec.bank, search='exact')
    ref = Classifier(rec.bank, search='exact', compiled=False)
    assert clf.path['head'] == 'compiled' and ref.path['head'] == 'reference'
    objects = load_demo_objects()
    rng = np.random.default_rng(11)
    feats = rec.encode([place_in_sensor_frame(x, rng, single_view=view)
                        for view in (False, True) for x in objects.xyz])
    with torch.no_grad():
        ref_prob, ref_novelty = ref._section(feats)
        prob, novelty = clf._section(feats)
        full = clf._evaluate(feats)
        full_ref = ref._evaluate(feats)
    # the same formulas; sums in double on both sides, the exponentials within 2 ulp
    torch.testing.assert_close(prob, ref_prob, atol=1e-6, rtol=0)
    torch.testing.assert_close(novelty, ref_novelty, atol=1e-7, rtol=0)
    assert torch.equal(prob.argmax(1), ref_prob.argmax(1))
    assert not torch.equal(prob, ref_prob)        # the compiled path ran, not the torch one
    torch.testing.assert_close(full[0], full_ref[0], atol=1e-6, rtol=0)
    # a row's result does not depend on its batch-mates
    head = clf.compiled_head
    z = clf.transform(feats[:6])
    u = clf.head.vote_space(z)
    whole, _ = head.finish_rows(u, z)
    for b in range(6):
        one, _ = head.finish_rows(u[b:b + 1], z[b:b + 1])
        assert np.array_equal(one[0], whole[b])
