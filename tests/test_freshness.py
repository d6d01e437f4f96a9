"""The freshness gate in every service's inbox (common/node.py), with an injected clock: forged
stamps, replays, clock steps and resynchronisation. No network; the same probes against the real
processes are in test_reliability.py."""
from __future__ import annotations

from common.inbox import Clock, FreshnessGate, FreshnessLimits, Inbox, Meta
from common.keys import topic

S = 1_000_000_000  # ns per s
T0 = 1_700_000_000 * S


class StepClock(Clock):
    """A wall clock the test steps at will and a monotonic clock that only moves forward."""

    def __init__(self) -> None:
        self.wall, self.mono = T0, 50 * S

    def wall_ns(self) -> int:
        return self.wall

    def mono_ns(self) -> int:
        return self.mono

    def advance(self, s: float) -> None:
        self.wall += int(s * S)
        self.mono += int(s * S)


def inbox(clock: StepClock, **limits) -> Inbox:
    return Inbox(topic("disparity"), FreshnessGate(clock, FreshnessLimits(**limits)), clock=clock)


class Stream:
    """A publisher: stamps from the (shared) wall clock, its own id and sequence."""

    def __init__(self, clock: StepClock, source: int):
        self.clock, self.source, self.seq = clock, source, 0

    def meta(self, stamp_ns: int | None = None) -> Meta:
        self.seq += 1
        return Meta(self.clock.wall_ns() if stamp_ns is None else stamp_ns, self.source, self.seq)


def deliver(box: Inbox, meta: Meta, payload: bytes = b"x") -> bool:
    """Offer, take and (as Node.take does after a successful decode) commit. -> handed on?"""
    box.offer(payload, meta)
    d = box.take_delivery(0)
    if d is None:
        return False
    return box.commit(d.meta.stamp_ns)


def test_a_forged_future_stamp_is_refused_and_costs_nothing_else():
    clock = StepClock()
    box, cam = inbox(clock), Stream(clock, 1)
    assert deliver(box, cam.meta())
    clock.advance(0.033)
    for forged in (2**64 - 1, clock.wall + 3600 * S):  # the probes: max stamp, one hour ahead
        assert not deliver(box, Meta(forged, 666, 1 if forged == 2**64 - 1 else 2))
    for _ in range(30):
        clock.advance(0.033)
        assert deliver(box, cam.meta()), "a real frame after a forged stamp must pass"
    assert box.gate.counts["future"] == 2 and box.gate.counts["late"] == 0


def test_garbage_with_a_plausible_stamp_never_becomes_the_reference():
    clock = StepClock()
    box, cam = inbox(clock), Stream(clock, 1)
    assert deliver(box, cam.meta())
    # slightly ahead (within max_future): accepted into the slot, but it does not decode, so it is
    # never committed: the next real frame is not "late"
    box.offer(b"garbage", Meta(clock.wall + int(0.2 * S), 7, 1))
    assert box.take_delivery(0).payload == b"garbage"
    clock.advance(0.033)
    assert deliver(box, cam.meta())


def test_a_flood_without_attachments_never_takes_the_slot_of_a_stamped_payload():
    # The CI failure it answers: garbage put on the obstacle key 200 times a second, without an
    # attachment, overwrote nearly every good list before a consumer could take it.
    clock = StepClock()
    box, cam = inbox(clock), Stream(clock, 1)
    for _ in range(20):
        clock.advance(0.033)
        box.offer(b"good", cam.meta())
        for _ in range(7):
            box.offer(b"\x00not msgpack\xff", None)
        d = box.take_delivery(0)
        assert d is not None and d.payload == b"good"
        box.commit(d.meta.stamp_ns)
        box.offer(b"\x00not msgpack\xff", None)  # nothing stamped waits: it may (it is decoded, then dropped)
        assert box.take_delivery(0).payload != b"good"
    assert box.unstamped == 20 * 7 and box.late == 0


def two_workers(clock: StepClock) -> tuple[Stream, Meta, Meta]:
    """Worker 1 and its frame's meta, then worker 2's of the next frame (33 ms on) -> (worker 1,
    the older meta, the newer one)."""
    w1, w2 = Stream(clock, 1), Stream(clock, 2)
    older = w1.meta(clock.wall)
    clock.advance(0.033)
    return w1, older, w2.meta(clock.wall)


def test_old_results_never_displace_newer_ones_and_replays_are_refused():
    clock = StepClock()
    box = inbox(clock)
    w1, older, newer = two_workers(clock)
    box.offer(b"new", newer)
    box.offer(b"old", older)  # a slow worker's older frame arrives after a newer one
    d = box.take_delivery(0)
    assert d.payload == b"new"
    box.commit(d.meta.stamp_ns)
    assert not deliver(box, w1.meta(older.stamp_ns))  # older than what was handed on
    assert not deliver(box, newer)                    # a replay of what was handed on
    assert box.gate.counts["late"] == 3


def test_an_older_result_that_passed_the_gate_while_a_newer_one_decoded_is_not_handed_on():
    # The CI failure it answers (three workers, one killed): the newer map was taken and decoding
    # when a slower worker's older one arrived; the slot was empty and the reference not yet moved,
    # so the older map waited, was handed on after the newer one and the obstacle lists went back.
    clock = StepClock()
    box = inbox(clock)
    w1, older, newer = two_workers(clock)
    box.offer(b"new", newer)
    taken = box.take_delivery(0)  # the receive loop decodes it ...
    box.offer(b"old", older)      # ... while the older map arrives: nothing newer waits or is committed
    assert box.commit(taken.meta.stamp_ns)
    d = box.take_delivery(0)
    assert d is not None and d.payload == b"old"
    assert not box.commit(d.meta.stamp_ns), "the older map must not follow the newer one out"
    assert box.gate.reference == newer.stamp_ns and box.gate.counts["late"] == 1 and box.late == 1
    clock.advance(0.033)
    assert deliver(box, w1.meta()), "the next frame passes"


def test_a_forged_sequence_number_cannot_poison_a_real_publisher():
    clock = StepClock()
    box, cam = inbox(clock), Stream(clock, 1)
    assert deliver(box, cam.meta())
    clock.advance(0.033)
    assert deliver(box, Meta(clock.wall, cam.source, 2**63))  # someone forges cam's id with a huge seq
    for _ in range(10):
        clock.advance(0.033)
        assert deliver(box, cam.meta())
    assert box.gate.counts["lost"] == 0


def test_a_stamp_far_in_the_past_is_refused_and_lost_messages_are_counted():
    clock = StepClock()
    box, cam = inbox(clock), Stream(clock, 1)
    assert not deliver(box, Meta(clock.wall - 3600 * S, 9, 1))
    assert deliver(box, cam.meta())
    cam.seq += 4  # four messages lost on the way
    clock.advance(0.1)
    assert deliver(box, cam.meta())
    assert box.gate.counts["old"] == 1 and box.gate.counts["lost"] == 4


def test_our_clock_stepping_back_costs_only_the_frames_in_flight():
    """NTP steps the robot's clock back 10 s: capture's stamps step with it. The reference (10 s
    ahead now) is dropped at once instead of refusing every frame for 10 s."""
    clock = StepClock()
    box, cam = inbox(clock), Stream(clock, 1)
    for _ in range(10):
        clock.advance(0.033)
        assert deliver(box, cam.meta())
    in_flight = cam.meta()  # captured just before the step
    clock.wall -= 10 * S
    clock.advance(0.033)
    assert not deliver(box, in_flight)  # now 10 s in the future: refused
    passed = 0
    for _ in range(10):
        clock.advance(0.033)
        passed += deliver(box, cam.meta())
    assert passed == 10
    assert box.gate.counts["clock_steps"] == 1


def test_a_sender_on_another_time_base_is_adopted_after_resync_s():
    """The capture host's clock is 10 s behind ours (or steps back while ours does not): every
    frame is 'old'. After resync_s of refusing everything the gate adopts that time base."""
    clock = StepClock()
    box, cam = inbox(clock, resync_s=1.0), Stream(clock, 1)
    assert deliver(box, cam.meta())
    refused_for = 0.0
    while not deliver(box, cam.meta(clock.wall - 10 * S)):
        clock.advance(0.033)
        refused_for += 0.033
        assert refused_for < 1.2, "never resynchronised"
    assert refused_for >= 0.99
    for _ in range(30):
        clock.advance(0.033)
        assert deliver(box, cam.meta(clock.wall - 10 * S))
    assert box.gate.counts["resyncs"] == 1
    # ages are in the adopted time base: a frame captured now is 0 s old, not 10 s
    assert box.gate.age_ns(clock.wall - 10 * S, clock.wall) == 0


def test_a_flood_of_forged_stamps_cannot_resync_the_gate_while_real_frames_pass():
    clock = StepClock()
    box, cam = inbox(clock, resync_s=0.5), Stream(clock, 1)
    forger = Stream(clock, 666)
    for _ in range(100):
        clock.advance(0.033)
        for _ in range(5):
            assert not deliver(box, forger.meta(clock.wall + 3600 * S))
        assert deliver(box, cam.meta())
    assert box.gate.counts["resyncs"] == 0 and box.gate.counts["future"] == 500


def test_a_starved_tracker_keeps_ids_of_what_it_had_no_frame_to_see():
    """Frames 1.5 s apart (a segmenter starved of CPU): a static obstacle is seen in every frame it
    gets, so it keeps its id; one that is really gone is dropped after timeout_s and 3 frames."""
    from cores.segmentation.tracking import Tracker

    tr = Tracker(timeout_s=1.0)
    box, other = [1.0, 0.0, 3.0], [-1.0, 0.0, 4.0]
    ids = {t.id for t in tr.update([box, other], 0.0)}
    for k in range(1, 6):
        ids |= {t.id for t in tr.update([box, other], 1.5 * k)}
    assert ids == {1, 2}
    for k in range(6, 9):
        assert [t.id for t in tr.update([box], 1.5 * k)] == [1]
    assert [t.id for t in tr.update([box, other], 1.5 * 9)] == [1, 3]  # gone 3 frames and 4.5 s: a new one


def test_node_frame_time_is_monotonic_across_a_wall_clock_step():
    """The tracker's time base: the capture moment on the monotonic clock, never going backwards."""
    from common.messages import ObstacleList
    from common.node import Node
    from common.zenoh_session import ZenohOptions

    clock = StepClock()
    node = Node("t", ZenohOptions(), "r", clock=clock)
    box, cam = Inbox(topic("disparity"), FreshnessGate(clock), clock=clock), Stream(clock, 1)
    times = []
    for k in range(20):
        clock.advance(0.033)
        if k == 10:
            clock.wall -= 10 * S  # NTP steps back; capture's stamps step with it
        meta = cam.meta()
        box.offer(b"x", meta)
        d = box.take_delivery(0)
        if d is None:
            continue
        box.commit(meta.stamp_ns)
        node._capture_mono[meta.stamp_ns] = d.mono_ns - box.gate.age_ns(meta.stamp_ns, d.wall_ns)
        msg = ObstacleList(robot_id="r", seq=k, stamp_ns=meta.stamp_ns, publish_ns=0, stale=False)
        times.append(node.frame_time_s(msg))
    steps = [b - a for a, b in zip(times, times[1:])]
    assert len(times) >= 19 and all(abs(s - 0.033) < 1e-6 for s in steps), steps


def test_calibrations_are_signed_with_the_robots_key_and_a_forgery_does_not_verify():
    from common.messages import CalibrationUpdate
    from common.signing import sign, signed

    key = b"robot-secret"
    msg = sign(CalibrationUpdate(robot_id="r", seq=0, stamp_ns=5, yaml="rectified: true\n", source="capture"), key)
    assert signed(msg, key) and not signed(msg, b"another key") and not signed(msg, b"")
    forged = msg.model_copy(update={"yaml": "rectified: true\nbaseline_m: 0.05\n"})
    assert not signed(forged, key)
    assert not signed(msg.model_copy(update={"signature": ""}), key)
