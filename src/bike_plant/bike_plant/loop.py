"""The loop nodes' shared transport pieces (plant, controller, session; no physics here):
the loop topics' QoS and HotWait, the wait on a node's hot topics; and the start-over on
fresh shared-memory ports that every node (the recorder too) uses after a stale port."""
from __future__ import annotations

import logging
import os
import time

import rclpy
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy

from . import shm_ports
from .config import LOOP_HISTORY_DEPTH

LOOP_QOS = QoSProfile(depth=LOOP_HISTORY_DEPTH, history=HistoryPolicy.KEEP_LAST,
                      reliability=ReliabilityPolicy.RELIABLE, durability=DurabilityPolicy.VOLATILE)
AUX_QOS = QoSProfile(depth=10, history=HistoryPolicy.KEEP_LAST, reliability=ReliabilityPolicy.RELIABLE)
# Realtime mode, the loop's readers (plant <- DriveCommand, controller <- PlantState): best
# effort. A reliable reader delivers in order, so a sample lost in transport would hold back
# every newer one until the writer repaired it. In real time a lost setpoint is held and the
# next one supersedes it; a late one is worse than none. The writers stay reliable, so a
# reliable reader (the recorder) still gets every sample.
REALTIME_QOS = QoSProfile(depth=10, history=HistoryPolicy.KEEP_LAST, reliability=ReliabilityPolicy.BEST_EFFORT,
                          durability=DurabilityPolicy.VOLATILE)


# Lockstep: a loop node polls for its answer this long before it blocks in the wait set. The
# answer comes within ~0.1-0.3 ms; blocking sleeps the thread and the wake-up goes through
# the kernel's futex and scheduler, and the node then runs on a cooled core: measured with
# the graph's own per-batch code in two processes (N = 20), 2.3-3.5x real time blocking,
# 4.9-7.0x polling; two such pairs on the 2 cores lose nothing to each other (each poll
# yields the core to any runnable thread). Realtime never polls (it waits for wall time).
LOCKSTEP_BUSY_WAIT_S = 0.001


def take_sim_time_from_messages(node) -> None:
    """use_sim_time off for a node of the graph. Each one takes sim time from what it reads (the
    plant is the clock; the controller, PlantState stamps; the session and the recorder, /clock
    through a reader of their own). rclpy's time source, which the configs' use_sim_time: true
    turns on, would add a second /clock reader to the node: one more delivery of every /clock,
    which the plant publishes inside the lockstep loop (every batch from N = 200 on)."""
    from rclpy.parameter import Parameter
    node.set_parameters([Parameter("use_sim_time", Parameter.Type.BOOL, False)])


def loop_reader_qos(sync_mode: str) -> QoSProfile:
    """QoS of a loop subscription: every sample in lockstep, the newest in realtime."""
    return REALTIME_QOS if sync_mode == "realtime" else LOOP_QOS


def recorder_progress(recorder_seq: int, reported: int, plant_k: int) -> int:
    """The recorder's written seq that lockstep flow control goes by, after a report.

    A report ahead of the plant's own batch ``plant_k`` is not this run's: the progress topic
    is latched (transient local), so a plant restarted mid-run first hears the last seq the
    recorder wrote of the previous run, and taking it would leave the new run unthrottled for
    that many batches (a slow recorder would then lose states)."""
    return recorder_seq if reported > plant_k else max(recorder_seq, reported)


def publisher_nodes(node, topic: str) -> set[tuple[str, str]]:
    """(name, namespace) of every node the graph lists as publishing ``topic`` (resolved)."""
    return {(i.node_name, i.node_namespace) for i in node.get_publishers_info_by_topic(topic)}


def recorder_reads(node, publisher, progress_topic: str = "recorder_progress") -> bool:
    """True once the recorder reads ``publisher``'s topic and the writer has matched it.

    The recorder is the node that publishes ``progress_topic``. The ROS graph (discovery
    info) can list a reader before this DDS writer has matched it, and samples sent meanwhile
    never reach it; ``get_subscription_count()`` is the writer's own matched count. So: a
    reader of the recorder's node is listed, and the writer has matched as many readers as
    the graph lists. Called while waiting to start, never per batch (graph queries are slow)."""
    recorders = publisher_nodes(node, node.resolve_topic_name(progress_topic))
    if not recorders:
        return False
    readers = node.get_subscriptions_info_by_topic(publisher.topic_name)
    if not any((i.node_name, i.node_namespace) in recorders for i in readers):
        return False
    return publisher.get_subscription_count() >= len(readers)


class HotWait:
    """The loop's wait: the few subscriptions a node waits on in its loop (the hot topics)
    taken straight from one rcl wait set, the pattern of rclpy's own wait_for_message.

    ``SingleThreadedExecutor.spin_once`` builds a new wait set over every entity of the node
    (parameter services, QoS event handlers of each publisher, ...) and runs a generator and a
    task per message: about 150 us of Python for each message, more than the message's DDS
    round trip on this machine, paid by the plant, the controller and the session on every
    batch. Here a message costs one wait and one take. The node's other entities (parameter
    services, timers, subscriptions that are not hot) are still served by ``executor``, which
    also sees the hot subscriptions (same callbacks): at most every ``aux_period_s`` wall
    seconds and whenever a wait ends without a hot message.

    Every hot callback is counted, whichever path ran it: a hot message that the executor's
    turn took must end the call like one taken here (else the wait below would sleep its
    whole timeout with the answer already in hand: 100 ms stalls, a third of the lockstep
    graph's wall time).

    A take that raises: a SIGINT that lands while rclpy converts the taken message raises its
    KeyboardInterrupt inside that conversion, and rclpy reports "Unable to convert call
    argument '0' to Python object" instead (the interrupt is lost; reproduced in 10 of 25
    Ctrl-Cs of a busy /clock loop; seen in CI as a session traceback when `bike run` stopped the
    graph). rclpy's handler has shut the context down by then, so with the context down the
    error is re-raised as the KeyboardInterrupt it was, and the node stops as on any Ctrl-C.
    Otherwise it is counted in ``take_errors`` and logged (the first, then every
    ``TAKE_ERROR_LOG_EVERY``-th): rcl has already taken that sample, the next one is taken on
    the next call, and the node lives on."""

    TAKE_ERROR_LOG_EVERY = 100
    TAKE_BURST = 64               # messages taken from one subscription before the next one's turn
    SHUTDOWN_GRACE_S = 0.05       # how long a failed take waits to see whether it was a Ctrl-C

    def __init__(self, executor, subscriptions, context, aux_period_s: float = 0.05,
                 logger=None):
        from rclpy.impl.implementation_singleton import rclpy_implementation as _rclpy

        self.executor = executor
        self.context = context
        self.subs = list(subscriptions)
        self.hot_callbacks = 0
        self.take_errors = 0
        self._log = logger or logging.getLogger(__name__)
        for sub in self.subs:
            sub.callback = self._counted(sub.callback)
        self.wait_set = _rclpy.WaitSet(len(self.subs), 0, 0, 0, 0, 0, context.handle)
        self.aux_period_s = aux_period_s
        self.next_aux = 0.0

    def replace(self, old, new) -> None:
        """Wait on subscription ``new`` in place of ``old`` (a node that re-creates one, e.g.
        with another QoS)."""
        new.callback = self._counted(new.callback)
        self.subs[self.subs.index(old)] = new

    def _counted(self, callback):
        def counted(msg):
            self.hot_callbacks += 1
            return callback(msg)
        return counted

    def _take_all(self) -> None:
        """Take every waiting message, in passes over the subscriptions (in their order: the
        controller's Commands before the PlantState that may need them) of at most
        TAKE_BURST each: a topic that keeps arriving faster than the reader drains it does
        not hold back the others (a lagging test reader got a realtime plant's states 0.2 s
        before the diagnostic published with the first of them)."""
        again = True
        while again:
            again = False
            for sub in self.subs:
                handle = sub.handle
                with handle:
                    for _ in range(self.TAKE_BURST):
                        try:
                            taken = handle.take_message(sub.msg_type, sub.raw)
                        except (RuntimeError, TypeError, ValueError) as exc:
                            self._take_failed(sub, exc)
                            break
                        if taken is None:
                            break
                        sub.callback(taken[0])
                    else:
                        again = True                 # more may be waiting: after the others'

    def _take_failed(self, sub, exc: Exception) -> None:
        # rclpy shuts the context down from its own signal thread: give it a moment
        deadline = time.monotonic() + self.SHUTDOWN_GRACE_S
        while self.context.ok() and time.monotonic() < deadline:
            time.sleep(0.005)
        if not self.context.ok():
            raise KeyboardInterrupt from None          # the interrupt rclpy's conversion swallowed
        self.take_errors += 1
        if self.take_errors % self.TAKE_ERROR_LOG_EVERY == 1:
            self._log.warning(f"could not take a message on {sub.topic_name}: {type(exc).__name__}: {exc}; "
                              f"skipped, the node goes on ({self.take_errors} such so far)")

    def spin(self, timeout_s: float, busy_s: float = 0.0) -> int:
        """Run the callback of every hot message waiting (waiting up to ``timeout_s`` for the
        first one); serve the rest of the node when due. Returns the hot messages handled.

        ``busy_s`` > 0: poll for the first message that long before blocking (see
        :data:`LOCKSTEP_BUSY_WAIT_S`), yielding the core to any other runnable thread between
        polls."""
        before = self.hot_callbacks
        now = time.monotonic()
        if now >= self.next_aux:
            self.next_aux = now + self.aux_period_s
            self.executor.spin_once(timeout_sec=0.0)
        self._take_all()
        handled = self.hot_callbacks - before
        if handled or timeout_s <= 0.0:
            return handled
        if busy_s > 0.0:
            until = time.perf_counter() + min(busy_s, timeout_s)
            while time.perf_counter() < until:
                os.sched_yield()
                self._take_all()
                handled = self.hot_callbacks - before
                if handled:
                    return handled
        ws = self.wait_set
        ws.clear_entities()
        for sub in self.subs:
            ws.add_subscription(sub.handle)
        ws.wait(int(timeout_s * 1e9))
        self._take_all()
        handled = self.hot_callbacks - before
        if not handled:
            self.next_aux = 0.0      # idle: the rest of the node is served on the next call
        return handled


UNNAMED_READER = "a reader whose node is not discovered yet"


class BusyWaitGuard:
    """The lockstep busy wait of one loop node, held while an observer reads its loop topics.

    Lockstep waits for the partner and the recorder only. While both loop nodes poll, both
    cores stay busy, and any other reader of a loop topic (``ros2 topic echo``, a monitor
    node, a test's reader) gets less CPU; one that falls more than the writer's history
    (LOOP_QOS depth) behind loses samples. So every ``check_s`` wall seconds the guard lists
    the readers of ``publishers``' topics: a reader in a node other than the partner (a
    publisher of ``partner_topic``, the topic this node waits on) and the recorder (the
    publisher of ``recorder_progress``) is an observer, and while one is there :meth:`busy_s`
    is 0 (the node blocks at once). A line is logged when polling stops or the observers
    change, and when it resumes. A graph query costs ~0.1 ms, once per ``check_s``, never
    per batch."""

    def __init__(self, node, publishers, partner_topic: str, busy_s: float, check_s: float = 1.0):
        self.node = node
        self.publishers = list(publishers)
        self.partner_topic = node.resolve_topic_name(partner_topic)
        self.progress_topic = node.resolve_topic_name("recorder_progress")
        self.configured_s = busy_s
        self.check_s = check_s
        self.next_check = 0.0
        self.observers: list[str] = []

    def _find_observers(self) -> list[str]:
        expected = publisher_nodes(self.node, self.partner_topic) | publisher_nodes(self.node, self.progress_topic)
        found = set()
        for pub in self.publishers:
            for i in self.node.get_subscriptions_info_by_topic(pub.topic_name):
                if (i.node_name, i.node_namespace) not in expected:
                    # the graph can list a reader before its node's name arrives: it counts (it
                    # may be an observer), and the log line comes again once it is named
                    found.add(UNNAMED_READER if i.node_name == "_NODE_NAME_UNKNOWN_"
                              else f"{i.node_namespace.rstrip('/')}/{i.node_name}")
        return sorted(found)

    def busy_s(self) -> float:
        """The busy wait for this wait: the configured one, or 0 while observed."""
        if self.configured_s <= 0.0:
            return 0.0
        now = time.monotonic()
        if now >= self.next_check:
            self.next_check = now + self.check_s
            try:
                observers = self._find_observers()
            except Exception:        # the context is shutting down: keep the last answer
                observers = self.observers
            if observers and observers != self.observers:
                topics = ", ".join(p.topic_name for p in self.publishers)
                self.node.get_logger().info(
                    f"{', '.join(observers)} read(s) {topics}: lockstep blocks instead of polling while "
                    "observed (a busy loop would starve an observer until it loses samples)")
            elif self.observers and not observers:
                self.node.get_logger().info(
                    f"no observer left: lockstep polls again (busy_wait_s = {self.configured_s:g})")
            self.observers = observers
        return 0.0 if self.observers else self.configured_s


HANDOVER_WAIT_S = 5.0    # a running node's new participant waits at most this long for its peers (wait_for_new_matches)


def _matched(endpoint) -> int:
    """The peers an rclpy publisher (its readers) or subscription (its writers) has matched."""
    count = getattr(endpoint, "get_subscription_count", None)
    return count() if count is not None else endpoint.get_publisher_count()


def wait_for_new_matches(pairs, wait=None, stop=None, timeout_s: float = HANDOVER_WAIT_S) -> list:
    """A running node that starts over on fresh ports goes on only once its new participant's
    endpoints have matched as many peers as the old one's did: what the new one sends before
    a reader has matched it never reaches that reader (the recorder's bag would have a hole).
    ``pairs``: (old, new) publishers or subscriptions; ``wait()`` runs between checks (default a
    20 ms sleep), ``stop()`` ends the wait early. Returns the topics of the new endpoints still
    behind after ``timeout_s`` (empty when all matched)."""
    until = time.monotonic() + timeout_s
    while True:
        late = [new.topic_name for old, new in pairs if _matched(new) < _matched(old)]
        if not late or time.monotonic() >= until or (stop is not None and stop()):
            return late
        if wait is None:
            time.sleep(0.02)
        else:
            wait()


def say_stale_peer_and_start_over(node, watch, publish_diag, goes_on: str = "") -> bool:
    """The running look of a node that already hears its peers (shm_ports.StalePeerWatch, due
    every DEAF_CHECK_S): when it fires, say so once, in the log (a warning) and in a WARN
    diagnostic (``publish_diag(text)``, each node's own), and ask for fresh ports
    (``node.fresh_ports_wanted``: start_over_on_fresh_ports follows). ``goes_on``: what the
    node keeps across the start over, appended to the text. True when it fired."""
    why = watch.look()
    if not why:
        return False
    text = f"{why}: starting over with a new DDS participant on fresh ports{goes_on}"
    node.get_logger().warning(text)
    publish_diag(text)
    node.fresh_ports_wanted = True
    return True


def start_over_on_fresh_ports(node_factory, old, args, old_executor=None, before_leaving=None):
    """A node that a live writer cannot reach over shared memory (Fast DDS's stale port after
    a kill -9, bike_plant.shm_ports) starts over in a new rclpy context: a new DDS participant,
    created while the old one still holds its ports, takes fresh ones, which the writer opens
    anew. Then the old participant leaves cleanly (the others drop it at once), and its ports'
    locks are held for the rest of the process, so no later participant inherits them.
    ``old_executor``: the old node's executor when it is not its ``executor_`` (session_node);
    ``before_leaving(node)``: runs while both participants are up (the recorder's hand-over)."""
    old_ports = shm_ports.own_ports()
    context = rclpy.Context()
    rclpy.init(args=args, context=context)
    node = node_factory(context=context)
    if before_leaving is not None:
        before_leaving(node)
    old_executor = old_executor or old.executor_
    old_executor.remove_node(old)
    old_executor.shutdown()
    old.destroy_node()
    rclpy.try_shutdown(context=old.context)
    held = shm_ports.hold_ports(old_ports)
    node.get_logger().info(f"on fresh shared-memory ports {shm_ports.own_ports()} (holding the old ones "
                           f"{held} for the rest of this process)")
    return node
