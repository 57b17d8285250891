"""coapkb.transport.coap.reliability.rto as a pure unit: every expected RTO below is computed by hand in
the comments (α = 1/8, β = 1/4, G = 0.1, K_strong = 4, K_weak = 1)."""

from __future__ import annotations

import json
import math
import random
from dataclasses import replace

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from coapkb.transport.coap.reliability.rto import (
    PROFILES,
    AdaptiveProfile,
    CocoaRto,
    FixedProfile,
    RetransmissionSchedule,
    RttEstimator,
    SampleKind,
    attribute_reply,
    backed_off_cap,
    classify_sample,
    get_profile,
    variable_backoff_factor,
    worst_case_wait,
)

approx = pytest.approx


# ------------------------------------------------------------ RttEstimator


def test_estimator_first_and_second_sample() -> None:
    e = RttEstimator(k=4)
    assert e.estimate is None
    # first R=0.2: SRTT=0.2, RTTVAR=0.1, E = 0.2 + max(0.1, 4·0.1) = 0.6
    assert e.update(0.2) == approx(0.6)
    assert (e.srtt, e.rttvar) == approx((0.2, 0.1))
    # R=0.6: RTTVAR = 0.75·0.1 + 0.25·|0.2−0.6| = 0.075 + 0.1 = 0.175 (old SRTT!)
    #        SRTT   = 0.875·0.2 + 0.125·0.6  = 0.175 + 0.075 = 0.25
    #        E      = 0.25 + 4·0.175 = 0.95
    assert e.update(0.6) == approx(0.95)
    assert (e.srtt, e.rttvar) == approx((0.25, 0.175))
    assert e.samples == 2


def test_estimator_granularity_floor_and_weak_k() -> None:
    # R=0.01: RTTVAR=0.005, 4·0.005 = 0.02 < G → E = 0.01 + 0.1 = 0.11
    assert RttEstimator(k=4).update(0.01) == approx(0.11)
    # weak K=1: R=1.0 → RTTVAR=0.5, E = 1.0 + max(0.1, 0.5) = 1.5
    assert RttEstimator(k=1).update(1.0) == approx(1.5)
    with pytest.raises(ValueError):
        RttEstimator(k=4).update(-0.1)


def test_classify_sample() -> None:
    assert classify_sample(0) is SampleKind.STRONG
    assert classify_sample(1) is classify_sample(2) is SampleKind.WEAK
    assert classify_sample(3) is classify_sample(9) is SampleKind.DISCARDED
    with pytest.raises(ValueError):
        classify_sample(-1)


# ------------------------------------------------------------ CocoaRto updates


def test_strong_weak_discarded_sequence() -> None:
    r = CocoaRto()
    assert r.rto(0.0) == 2.0 and not r.has_samples
    # strong R=0.2 @1: E_s = 0.6 (see above); RTO = 0.5·0.6 + 0.5·2.0 = 1.3
    assert r.on_sample(0.2, 0, now=1.0) is SampleKind.STRONG
    assert r.rto(1.0) == approx(1.3)
    # strong R=0.2 @2: RTTVAR = 0.75·0.1 + 0 = 0.075, SRTT = 0.2,
    #   E_s = 0.2 + 4·0.075 = 0.5; RTO = 0.5·0.5 + 0.5·1.3 = 0.9
    r.on_sample(0.2, 0, now=2.0)
    assert r.rto(2.0) == approx(0.9)
    # weak R=1.0 (1 retx) @3 (idle 1 s < 16·0.9, no ageing):
    #   E_w = 1.0 + max(0.1, 1·0.5) = 1.5; RTO = 0.25·1.5 + 0.75·0.9 = 0.375 + 0.675 = 1.05
    assert r.on_sample(1.0, 1, now=3.0) is SampleKind.WEAK
    assert r.rto(3.0) == approx(1.05)
    # 3 retransmissions: discarded, nothing changes (not even last_update)
    assert r.on_sample(0.3, 3, now=4.0) is SampleKind.DISCARDED
    assert r.rto(4.0) == approx(1.05) and r.last_update == 3.0
    assert (r.strong.samples, r.weak.samples) == (2, 1)
    # weak R=2.0 (2 retx) @5: RTTVAR_w = 0.75·0.5 + 0.25·|1.0−2.0| = 0.625
    #   SRTT_w = 0.875·1.0 + 0.125·2.0 = 1.125; E_w = 1.125 + 0.625 = 1.75
    #   RTO = 0.25·1.75 + 0.75·1.05 = 0.4375 + 0.7875 = 1.225
    r.on_sample(2.0, 2, now=5.0)
    assert r.rto(5.0) == approx(1.225)
    # min_rtt tracks raw strong samples only
    assert r.min_rtt == approx(0.2)


def test_kind_override_makes_a_retransmitted_sample_strong() -> None:
    r = CocoaRto()
    # as the first strong sample: RTO = 0.5·0.6 + 0.5·2.0 = 1.3, despite 1 retransmission
    assert r.on_sample(0.2, 1, now=0.0, kind=SampleKind.STRONG) is SampleKind.STRONG
    assert r.rto(0.0) == approx(1.3)


def test_rto_cap_32() -> None:
    r = CocoaRto()
    # strong R=40: E = 40 + 4·20 = 120; RTO = 60 + 1 = 61 → capped at 32
    r.on_sample(40.0, 0, now=0.0)
    assert r.rto(0.0) == 32.0
    w = CocoaRto()
    # weak R=40: E = 40 + 20 = 60; RTO = 0.25·60 + 0.75·2 = 16.5 (under the cap)
    w.on_sample(40.0, 1, now=0.0)
    assert w.rto(0.0) == approx(16.5)


def test_size_normalisation() -> None:
    r = CocoaRto(link_rate_bps=32_000)
    # 1000 B at 32 kbit/s = 8000/32000 = 0.25 s of serialisation
    assert r.serialisation_time(1000) == approx(0.25)
    # R=0.35 with 1000 B on the wire → base 0.1: E = 0.1 + max(0.1, 4·0.05) = 0.3
    #   RTO = 0.5·0.3 + 0.5·2.0 = 1.15; min_rtt keeps the raw 0.35
    r.on_sample(0.35, 0, now=0.0, wire_bytes=1000)
    assert r.rto(0.0) == approx(1.15)
    assert r.min_rtt == approx(0.35)
    # the next 1000-byte exchange gets its serialisation back on top of the dither:
    #   [1.15 + 0.25, 1.5·1.15 + 0.25] = [1.4, 1.975]
    assert r.initial_timeout_range(0.0, wire_bytes=1000) == approx((1.4, 1.975))
    # a sample shorter than its own serialisation counts as 0 (rate set too low):
    #   E = 0 + max(0.1, 0) = 0.1; RTO = 0.05 + 1.0 = 1.05
    z = CocoaRto(link_rate_bps=32_000)
    z.on_sample(0.2, 0, now=0.0, wire_bytes=1000)
    assert z.rto(0.0) == approx(1.05)
    # without a link rate wire_bytes is ignored: plain CoCoA
    p = CocoaRto()
    p.on_sample(0.35, 0, now=0.0, wire_bytes=1000)
    # E = 0.35 + 4·0.175 = 1.05; RTO = 0.525 + 1.0 = 1.525
    assert p.rto(0.0) == approx(1.525)


# ------------------------------------------------------------ dithering, clamps, blind start, VBF


def test_dithering_bounds() -> None:
    rng = random.Random(1)
    r = CocoaRto()
    draws = [r.initial_timeout(rng, now=0.0) for _ in range(2000)]
    # uniform[RTO, 1.5·RTO] with RTO = 2 → [2, 3], spread over the whole range
    assert all(2.0 <= d <= 3.0 for d in draws)
    assert min(draws) < 2.05 and max(draws) > 2.95


def test_lower_and_upper_clamp() -> None:
    rng = random.Random(2)
    # RTO 0.1 → uniform[0.1, 0.15] → always clamped up to 0.5
    low = CocoaRto(initial_rto=0.1)
    assert {low.initial_timeout(rng, now=0.0) for _ in range(100)} == {0.5}
    # RTO 32 plus 16 s of serialisation (2000 B at 1 kbit/s): [48, 64] → clamp at 60
    high = CocoaRto(initial_rto=32.0, link_rate_bps=1000)
    draws = [high.initial_timeout(rng, now=0.0, wire_bytes=2000) for _ in range(500)]
    assert all(48.0 <= d <= 60.0 for d in draws) and draws.count(60.0) > 100
    # a lab floor can be configured
    lab = CocoaRto(initial_rto=0.1, min_timeout=0.05)
    assert 0.1 <= lab.initial_timeout(rng, now=0.0) <= 0.15


def test_blind_start_multiplies_by_outstanding_until_first_sample() -> None:
    rng = random.Random(3)
    r = CocoaRto()
    # 3 outstanding: 2·3 = 6 → [6, 9]
    assert all(6.0 <= r.initial_timeout(rng, 0.0, outstanding=3) <= 9.0 for _ in range(100))
    # 20 outstanding: 40 → capped at 32 → [32, 48]
    assert all(32.0 <= r.initial_timeout(rng, 0.0, outstanding=20) <= 48.0 for _ in range(100))
    # after a sample the multiplier no longer applies: RTO 1.3 → [1.3, 1.95]
    r.on_sample(0.2, 0, now=0.0)
    assert all(1.3 <= r.initial_timeout(rng, 0.0, outstanding=5) <= 1.95 for _ in range(100))


@pytest.mark.parametrize(
    "initial, factor",
    [(0.5, 3.0), (0.999, 3.0), (1.0, 2.0), (2.0, 2.0), (3.0, 2.0), (3.001, 1.5), (40.0, 1.5)],
)
def test_variable_backoff_factor(initial: float, factor: float) -> None:
    assert variable_backoff_factor(initial) == factor
    assert CocoaRto.backoff_factor(initial) == factor


def test_schedule_backoff_and_cap() -> None:
    # VBF 3 from 0.5 s, each timeout capped at 60 s:
    #   0.5, 1.5, 4.5, 13.5, 40.5, min(121.5, 60), min(364.5, 60) → total 180.5
    s = RetransmissionSchedule(initial_timeout=0.5, backoff_factor=3.0, max_retransmit=6, max_timeout=60.0)
    assert s.timeouts() == approx((0.5, 1.5, 4.5, 13.5, 40.5, 60.0, 60.0))
    assert s.total_wait == approx(180.5)
    assert s.transmit_offsets == approx((0.0, 0.5, 2.0, 6.5, 20.0, 60.5, 120.5))


# ------------------------------------------------------------ ageing


def test_ageing_up_doubles_small_rto_per_idle_period() -> None:
    r = CocoaRto(initial_rto=0.25, last_update=0.0)
    # 0.25 < 1 s: after 16·0.25 = 4 s idle → 0.5; then after 16·0.5 = 8 s more (t=12) → 1.0
    assert r.rto(3.9) == 0.25
    assert r.rto(4.0) == 0.5
    assert r.rto(11.9) == 0.5
    assert r.rto(12.0) == 1.0
    assert r.rto(1000.0) == 1.0  # 1.0 is not < 1 s: no more ageing
    # one lazy call over the whole silence applies both steps
    j = CocoaRto(initial_rto=0.25, last_update=0.0)
    assert j.rto(12.0) == 1.0 and j.last_update == 12.0


def test_ageing_down_halves_large_rto_towards_one_second() -> None:
    r = CocoaRto(initial_rto=20.0, last_update=0.0)
    # > 3 s: every 4·RTO idle → 1 + RTO/2
    #   t=80 (4·20): 11;  t=124 (+4·11): 6.5;  t=150 (+4·6.5): 4.25;
    #   t=167 (+4·4.25): 3.125;  t=179.5 (+4·3.125): 2.5625, which is ≤ 3: stop
    assert r.rto(79.9) == 20.0
    assert r.rto(80.0) == 11.0
    assert r.rto(124.0) == 6.5
    assert r.rto(150.0) == 4.25
    assert r.rto(167.0) == 3.125
    assert r.rto(179.5) == 2.5625
    assert r.rto(10_000.0) == 2.5625
    j = CocoaRto(initial_rto=20.0, last_update=0.0)
    assert j.rto(179.5) == 2.5625


def test_ageing_applies_before_a_sample_and_not_before_the_first() -> None:
    r = CocoaRto(initial_rto=0.25, last_update=0.0)
    # aged to 0.5 at t=4, then strong R=0.2: RTO = 0.5·0.6 + 0.5·0.5 = 0.55
    r.on_sample(0.2, 0, now=4.0)
    assert r.rto(4.0) == approx(0.55)
    fresh = CocoaRto(initial_rto=0.25)  # no sample yet: nothing to age
    assert fresh.rto(1e6) == 0.25


# ------------------------------------------------------------ spurious attribution


def test_attribute_reply() -> None:
    # threshold = 0.5 · min_rtt 0.2 = 0.1 s
    t = [0.0, 0.5, 2.0]
    assert attribute_reply(t, 2.05, min_rtt=0.2) == 1  # 0.05 after retx 2: answers ≤ retx 1
    assert attribute_reply(t, 2.30, min_rtt=0.2) == 2  # plausible for the last copy
    assert attribute_reply([0.0, 0.5], 0.55, min_rtt=0.2) == 0  # the original: strong sample
    assert attribute_reply(t, 0.01, min_rtt=0.2) == 0  # impossible-fast: still the original
    assert attribute_reply(t, 2.05, min_rtt=None) == 2  # no evidence


# ------------------------------------------------------------ profiles


def test_worst_case_wait_handles_non_monotonic_vbf() -> None:
    # initial in [0.5, 1.2], 4 retransmissions, cap 60:
    #   at 1.2 (×2): 1.2·(1+2+4+8+16) = 37.2
    #   just below 1 (×3): 1+3+9+27+min(81,60) = 100  ← the supremum
    assert worst_case_wait(0.5, 1.2, 4, 60.0) == approx(100.0)
    # fixed factor: monotonic, so it is the top of the range: 3·31 = 93
    assert worst_case_wait(2.0, 3.0, 4, math.inf, backoff_factor=2.0) == approx(93.0)


def test_adaptive_backoff_cap() -> None:
    rng = random.Random(5)
    capped, plain = AdaptiveProfile(), AdaptiveProfile(backoff_cap=None)
    assert capped.backoff_cap == 8.0 and capped.as_dict()["backoff_cap"] == 8.0
    rto = capped.new_rto()
    for _ in range(20):
        rto.on_sample(0.001, 0, now=0.0)
    # from the 0.5 s clamp, ×3: 0.5, 1.5, 4.5, then capped at 8 (plain CoCoA: 13.5, 40.5, 60, 60)
    s = capped.schedule(rng, rto, now=0.0)
    assert s.timeouts() == approx((0.5, 1.5, 4.5, 8.0, 8.0, 8.0, 8.0)) and s.total_wait == approx(38.5)
    assert plain.schedule(rng, rto, now=0.0).timeouts() == approx((0.5, 1.5, 4.5, 13.5, 40.5, 60.0, 60.0))
    # an initial timeout above the cap is never shortened; it just does not grow
    slow = CocoaRto(initial_rto=10.0)
    s = capped.schedule(rng, slow, now=0.0)
    assert 10.0 <= s.initial_timeout <= 15.0 and set(s.timeouts()) == {s.initial_timeout}
    assert backed_off_cap(0.5, 60.0, 8.0) == 8.0 and backed_off_cap(12.0, 60.0, 8.0) == 12.0
    assert backed_off_cap(90.0, 60.0, 8.0) == 60.0 and backed_off_cap(0.5, 60.0, None) == 60.0
    # the bound over a range crossing the cap: worst at the top, 7·9 = 63
    assert worst_case_wait(0.5, 9.0, 6, 60.0, backoff_cap=8.0) == approx(63.0)
    # below the cap the VBF bands still decide: [0.5, 1.2] → just below 1 s (×3): 1+3+8·5 = 44
    assert worst_case_wait(0.5, 1.2, 6, 60.0, backoff_cap=8.0) == approx(44.0)
    with pytest.raises(ValueError):
        AdaptiveProfile(backoff_cap=0.0)


def test_profiles_registry_and_bounds() -> None:
    assert set(PROFILES) == {"rfc7252", "lossy-fixed", "adaptive"}
    rfc = PROFILES["rfc7252"]
    # RFC 7252 §4.8.2: MAX_TRANSMIT_SPAN = 2·(2⁴−1)·1.5 = 45, MAX_TRANSMIT_WAIT = 2·(2⁵−1)·1.5 = 93
    assert (rfc.max_transmit_span(), rfc.max_transmit_wait()) == approx((45.0, 93.0))
    lossy = PROFILES["lossy-fixed"]
    # worst initial 0.8·1.25 = 1.0: 1, 2, 4, 8, 8, 8, 8 → 39 s (span: minus the last 8 → 31)
    assert (lossy.max_transmit_span(), lossy.max_transmit_wait()) == approx((31.0, 39.0))
    adaptive = PROFILES["adaptive"]
    # worst initial 1.5·32 = 48 (×1.5), above the 8 s backoff cap, so every
    # timeout stays 48: 7·48 = 336.  Plain CoCoA (no cap): 48 + 6·60 = 408.
    assert adaptive.max_transmit_wait() == approx(336.0)
    assert replace(adaptive, backoff_cap=None).max_transmit_wait() == approx(408.0)
    for profile in PROFILES.values():
        d = profile.as_dict()
        json.dumps(d)
        assert d["name"] and d["kind"] in ("fixed", "adaptive") and d["max_transmit_wait"] > 0
    assert get_profile("adaptive") is adaptive and get_profile(lossy) is lossy
    with pytest.raises(ValueError):
        get_profile("fast")


def test_profile_schedules() -> None:
    rng = random.Random(4)
    lossy = PROFILES["lossy-fixed"]
    s = lossy.schedule(rng, lossy.new_rto(), now=0.0)
    assert 0.8 <= s.initial_timeout <= 1.0 and s.backoff_factor == 2.0 and s.max_timeout == 8.0
    assert s.timeouts()[-3:] == (8.0, 8.0, 8.0)
    adaptive = AdaptiveProfile()
    rto = adaptive.new_rto()
    s = adaptive.schedule(rng, rto, now=0.0)  # RTO 2 → [2, 3], ×2
    assert 2.0 <= s.initial_timeout <= 3.0 and s.backoff_factor == 2.0
    for _ in range(20):
        rto.on_sample(0.001, 0, now=0.0)
    s = adaptive.schedule(rng, rto, now=0.0)  # converged: clamp 0.5, ×3
    assert (s.initial_timeout, s.backoff_factor) == (0.5, 3.0)
    # the per-peer bound is then much tighter than the static one (×3 from
    # the clamp, capped at 8 s):
    #   0.5, 1.5, 4.5, 8, 8, 8, 8 = 38.5   (plain CoCoA: 0.5, 1.5, 4.5, 13.5, 40.5, 60, 60 = 180.5)
    assert adaptive.max_transmit_wait_for(rto, now=0.0) == approx(38.5)
    assert replace(adaptive, backoff_cap=None).max_transmit_wait_for(rto, now=0.0) == approx(180.5)
    fast = adaptive.with_link_rate(35_000)
    assert fast.new_rto().link_rate_bps == 35_000 and fast.as_dict()["link_rate_bps"] == 35_000
    with pytest.raises(ValueError):
        FixedProfile(name="bad", ack_timeout=0.0, ack_random_factor=1.0, max_retransmit=1)


@settings(max_examples=200, deadline=None)
@given(
    st.lists(
        st.tuples(st.floats(0.0, 100.0), st.integers(0, 5), st.floats(0.0, 500.0), st.integers(0, 3000)),
        max_size=40,
    ),
    st.integers(0, 2**32 - 1),
)
def test_invariants_hold_for_any_sample_sequence(samples: list[tuple[float, int, float, int]], seed: int) -> None:
    rng = random.Random(seed)
    r = CocoaRto(link_rate_bps=35_000)
    now = 0.0
    for rtt, retx, gap, wire in samples:
        now += gap
        r.on_sample(rtt, retx, now=now, wire_bytes=wire)
        assert 0.0 < r.rto(now) <= 32.0
        t0 = r.initial_timeout(rng, now, wire_bytes=wire)
        assert 0.5 <= t0 <= 60.0
