"""Class-size prior of the kernel vote for enrolled classes (bank/vote_prior.py, issue 12)."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
import torch

from point_gn_ros.bank.classifier import Classifier
from point_gn_ros.bank.enroll import (BankFile, RefitPolicy, add_examples, class_counts,
                                      remove_class)
from point_gn_ros.bank.sections import combine_sections
from point_gn_ros.bank.store import FeatureBank
from point_gn_ros.bank.transform import FeatureTransform
from point_gn_ros.bank.vote_prior import META_KEY, vote_log_bias
from point_gn_ros.core.config import EncoderConfig

D = EncoderConfig().feature_dim
SIZES = (400, 40, 40, 40)      # one big category, three small classes


def _category_bank(gamma: float = 4.0, seed: int = 0) -> tuple[FeatureBank, torch.Tensor,
                                                                torch.Tensor]:
    """A wide-kernel bank whose class 'cat' has 10x the entries of the others.

    -> (bank, raw features (N, D), class centres (4, D)).
    """
    g = torch.Generator().manual_seed(seed)
    centres = torch.randn(len(SIZES), D, generator=g)
    labels = torch.cat([torch.full((n,), i) for i, n in enumerate(SIZES)])
    feats = centres[labels] + 0.9 * torch.randn(len(labels), D, generator=g)
    tf = FeatureTransform.fit(feats, 'standardize')
    bank = FeatureBank(features=tf(feats), labels=labels, class_names=['cat', 'b', 'c', 'd'],
                       config=EncoderConfig(), transform=tf, gamma=gamma, meta={})
    return bank, feats, centres


@pytest.fixture(scope='module')
def instance() -> dict[str, torch.Tensor | BankFile]:
    """The bank, 5 examples of one member ('mine') of 'cat', 20 other looks at it, 50 cats."""
    bank, _, centres = _category_bank()
    g = torch.Generator().manual_seed(7)
    mine = centres[0] + 0.9 * torch.randn(D, generator=g)
    return {'bf': BankFile.of(bank, 'float32'),
            'examples': mine + 0.6 * torch.randn(5, D, generator=g),
            'looks': mine + 0.6 * torch.randn(20, D, generator=g),
            'cats': centres[0] + 0.9 * torch.randn(50, D, generator=g)}


def _enrolled(inst: dict, beta: float) -> BankFile:
    return add_examples(inst['bf'], inst['examples'], 'mine',
                        policy=RefitPolicy(gamma='keep', vote_prior=beta)).file


def test_instance_outvoted_by_its_category_without_the_prior(instance: dict) -> None:
    plain, prior = _enrolled(instance, 0.0), _enrolled(instance, 1.0)
    assert META_KEY not in plain.bank.meta                 # nothing recorded when off
    assert prior.bank.meta[META_KEY] == {'beta': 1.0, 'classes': ['mine']}
    assert prior.bank.meta['refit']['vote_prior'] == 1.0
    looks = instance['looks']
    # 400 category entries outweigh 5 close ones: every look at 'mine' is called 'cat' ...
    assert (Classifier(plain.bank).classify(looks).labels == 0).all()
    # ... with the prior 'mine' counts as an average-size class and wins its own looks,
    assert (Classifier(prior.bank).classify(looks).labels == 4).all()
    # while other members of the category stay 'cat'.
    assert (Classifier(prior.bank).classify(instance['cats']).labels == 0).all()


def test_bias_is_the_documented_formula_and_only_on_listed_classes(instance: dict) -> None:
    bank = _enrolled(instance, 1.5).bank
    bias = vote_log_bias(bank.meta, bank.class_names, bank.labels)
    n_ref = np.mean(SIZES)                                  # mean of the unlisted classes
    expected = np.zeros(5, dtype=np.float32)
    expected[4] = 1.5 * np.log(n_ref / 5)
    np.testing.assert_allclose(bias.numpy(), expected, rtol=1e-6)
    assert vote_log_bias({}, bank.class_names, bank.labels) is None
    zero = {META_KEY: {'beta': 0.0, 'classes': ['mine']}}
    assert vote_log_bias(zero, bank.class_names, bank.labels) is None
    with pytest.raises(ValueError, match='beta'):
        vote_log_bias({META_KEY: {'beta': -1, 'classes': ['mine']}}, bank.class_names,
                      bank.labels)
    with pytest.raises(ValueError, match='vote_prior'):
        RefitPolicy(vote_prior=-0.5)


def test_built_classes_keep_their_relative_votes(instance: dict) -> None:
    plain, prior = _enrolled(instance, 0.0), _enrolled(instance, 1.0)
    q = instance['cats']
    p0 = Classifier(plain.bank).scores(q)[:, :4]
    p1 = Classifier(prior.bank).scores(q)[:, :4]
    # Only the listed class moves: the built classes' probabilities keep their ratios.
    torch.testing.assert_close(p0 / p0.sum(1, keepdim=True), p1 / p1.sum(1, keepdim=True))


def test_indexed_and_exact_search_agree_and_batch_invariant(instance: dict) -> None:
    bank = _enrolled(instance, 1.0).bank
    q = torch.cat([instance['looks'], instance['cats']])
    exact = Classifier(bank, search='exact')
    indexed = Classifier(bank, search='indexed')
    assert exact.vote_bias is not None and indexed.vote_bias is not None
    np.testing.assert_array_equal(exact.classify(q).labels, indexed.classify(q).labels)
    torch.testing.assert_close(exact.scores(q), indexed.scores(q), atol=1e-5, rtol=0)
    # a lone query takes the compiled path (bank/lone.py), a batch torch's: the same prior
    one_by_one = torch.cat([indexed.scores(q[i:i + 1]) for i in range(len(q))])
    torch.testing.assert_close(one_by_one, indexed.scores(q), atol=1e-6, rtol=0)
    assert torch.equal(one_by_one.argmax(1), indexed.scores(q).argmax(1))


def test_saved_bank_keeps_the_prior_bit_for_bit(instance: dict, tmp_path) -> None:  # noqa: ANN001
    bf = _enrolled(instance, 1.0)
    path = bf.save(tmp_path / 'b.npz')
    loaded = BankFile.load(path)
    assert loaded.bank.meta[META_KEY] == bf.bank.meta[META_KEY]
    q = instance['looks']
    assert torch.equal(Classifier(loaded.bank).scores(q), Classifier(bf.bank).scores(q))


def test_more_examples_keep_the_listing_and_remove_drops_it(instance: dict) -> None:
    bf = _enrolled(instance, 1.0)
    # A later add under a policy without the prior keeps the class listed (recorded choice).
    more = add_examples(bf, instance['looks'][:2], 'mine', policy=RefitPolicy(gamma='keep'))
    assert more.bank.meta[META_KEY]['classes'] == ['mine']
    # A built class never gets the prior, whatever the policy.
    built = add_examples(bf, instance['cats'][:3], 'cat',
                         policy=RefitPolicy(gamma='keep', vote_prior=1.0))
    assert built.bank.meta[META_KEY]['classes'] == ['mine']
    gone = remove_class(more.file, 'mine', policy=RefitPolicy(gamma='keep'))
    assert META_KEY not in gone.bank.meta and 'mine' not in class_counts(gone.bank)


def test_two_section_bank_lists_the_class_in_both_sections(instance: dict) -> None:
    bank, feats, _ = _category_bank(seed=0)
    views, vfeats, _ = _category_bank(seed=1)
    views = replace(views, transform=bank.transform, features=bank.transform(vfeats))
    both = combine_sections(bank, views, torch.cat([feats, vfeats]),
                            np.r_[np.zeros(len(feats), bool), np.ones(len(vfeats), bool)])
    res = add_examples(BankFile.of(both, 'float32'), instance['examples'], 'mine',
                       policy=RefitPolicy(gamma='keep', vote_prior=1.0))
    assert res.bank.meta[META_KEY]['classes'] == ['mine']
    assert res.bank.views.meta[META_KEY]['classes'] == ['mine']
    clf = Classifier(res.bank)
    assert clf.vote_bias is not None and clf.views.vote_bias is not None
