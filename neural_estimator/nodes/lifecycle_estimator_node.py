"""Lifecycle estimator node: the estimator as a managed node, for teams that bring nodes up with a
lifecycle manager (nav2's lifecycle_manager, ``ros2 lifecycle set``).

    ros2 run neural_estimator lifecycle_estimator --ros-args -p method:=ukf -p scenario:=bearings
    ros2 lifecycle set /lifecycle_estimator configure   # builds the filter / loads the model
    ros2 lifecycle set /lifecycle_estimator activate    # subscribes and publishes

Transitions (rclpy.lifecycle, ``lifecycle_msgs``): **configure** checks the parameters and builds
the method (a filter, or a neural model from its checkpoint: the slow part, done before the robot
needs it); a bad method, scenario or checkpoint fails the transition in one logged line and the
node stays unconfigured. **activate** creates the estimate publishers (the estimator node's
topics and standard outputs, :mod:`neural_estimator.nodes.outputs`) and the observation
subscription; **deactivate** destroys them (observations are not received while inactive);
**cleanup** drops the method; **shutdown** from any state. A transition the current state does not
have (configure twice, activate before configure, cleanup while active), requested through the
``change_state`` service by id or label, is answered ``success=False`` with one WARN line naming
the state and the transitions it has; the node stays where it was. Same parameters as the estimator node
(``params/estimator.yaml``), except that ``scenario`` must be given: configure needs the system.
Configure and activate run the estimator node's own setup (:mod:`neural_estimator.nodes.estimator_setup`:
the same checks of the parameters, method options, ``init``, ``preset``, ``threads`` and warm-up, the
same standard outputs), and the per-message work is :class:`neural_estimator.stream.online.OnlineEstimator`,
as in the estimator node.
"""

from __future__ import annotations

import sys

from rclpy.lifecycle import LifecycleNode, LifecycleState, TransitionCallbackReturn
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
from sensor_msgs.msg import JointState

from neural_estimator.stream import messages as MSG
from neural_estimator.bags.errors import MessageError
from neural_estimator.methods.registry import EstimatorError
from neural_estimator.nodes.common import (
    StartupError,
    build_scenario,
    declare_params,
    load_plugins,
    run_node,
    stream_qos,
    warn_throttled,
)
from neural_estimator.nodes.estimator_params import EstimatorParams
from neural_estimator.nodes.estimator_setup import (
    build_online,
    checked_method,
    model_note,
    publish_result,
    standard_outputs,
)
from neural_estimator.nodes.outputs import OutputParams, Outputs
from neural_estimator.stream.online import OnlineEstimator


class LifecycleEstimatorNode(LifecycleNode):
    def __init__(self, node_name: str = "lifecycle_estimator") -> None:
        super().__init__(node_name)
        self.p = declare_params(self, EstimatorParams)
        self.po = declare_params(self, OutputParams)
        self.online: OnlineEstimator | None = None
        self.entities: list = []  # publishers and the subscription of the active state
        self.outputs: Outputs | None = None
        self.counts = {"estimates": 0, "bad": 0, "skipped": 0}
        self._last_log: dict[str, float] = {}
        # rclpy's change_state service triggers a transition id without checking that the current
        # state has it; the state machine then raises "Transition is not registered" out of the
        # service callback, which kills the node. The check goes in front of that callback.
        self._service_change_state.callback = self._guard_change_state(self._service_change_state.callback)

    def _guard_change_state(self, change_state):
        def guarded(req, resp):
            available = {t[0]: t[1] for t in self._state_machine.available_transitions}
            label = req.transition.label
            if (label and label not in available.values()) or (not label and req.transition.id not in available):
                _, state = self._state_machine.current_state
                asked = repr(label) if label else f"id {req.transition.id}"
                self.get_logger().warning(
                    f"change_state refused: transition {asked} is not available in state {state!r} "
                    f"(available: {', '.join(sorted(available.values())) or 'none'})"
                )
                resp.success = False
                return resp
            return change_state(req, resp)

        return guarded

    # ---- transitions ---------------------------------------------------------------------------------
    def on_configure(self, state: LifecycleState) -> TransitionCallbackReturn:
        p = self.p
        try:  # the estimator node's setup (estimator_setup), here at configure
            method = checked_method(p)
            if not p.scenario:
                raise StartupError("parameter scenario is required by the lifecycle estimator (configure builds it)")
            load_plugins(p.plugins)
            scenario = build_scenario(p.scenario, p.set, preset=p.preset)
            _, online = build_online(method, scenario, p)
        except (EstimatorError, StartupError, ValueError) as exc:
            self.get_logger().error(f"configure failed: {exc}")
            return TransitionCallbackReturn.FAILURE
        self.method = method
        self.online = online
        self.get_logger().info(f"configured: {method} on {scenario.name}{model_note(method, p)}")
        return TransitionCallbackReturn.SUCCESS

    def on_activate(self, state: LifecycleState) -> TransitionCallbackReturn:
        p, scenario = self.p, self.online.scenario
        out = p.output_topic or MSG.estimate_topic(self.method)
        qos = stream_qos(p.history_depth)
        try:
            self.outputs = standard_outputs(self, self.po, p, out, qos, scenario)
        except StartupError as exc:
            self.get_logger().error(f"activate failed: {exc}")
            return TransitionCallbackReturn.FAILURE
        self.pub_est = self.create_publisher(JointState, out, qos)
        self.pub_cov = None
        if self.online.publish_covariance:
            self.pub_cov = self.create_publisher(JointState, f"{out}/{MSG.COVARIANCE_SUFFIX}", qos)
        sub_qos = QoSProfile(
            depth=max(1, p.queue_depth),
            reliability=ReliabilityPolicy.RELIABLE
            if p.observation_qos == "reliable"
            else ReliabilityPolicy.BEST_EFFORT,
            durability=DurabilityPolicy.VOLATILE,  # matches any publisher; history is not replayed here
        )
        self.sub = self.create_subscription(JointState, p.observation_topic, self._on_observation, sub_qos, raw=True)
        # a held jump that nothing confirms or refutes is accepted once the stream falls silent
        self.quarantine_timer = self.create_timer(0.1, self._on_quarantine)
        o = self.outputs
        self.entities = [self.pub_est, self.pub_cov, self.sub, o.pub_odom, o.pub_pose, o.pub_state, o.pub_tf]
        self.get_logger().info(f"active: '{self.sub.topic_name}' -> '{self.pub_est.topic_name}'{o.describe()}")
        return super().on_activate(state)

    def on_deactivate(self, state: LifecycleState) -> TransitionCallbackReturn:
        self._destroy_entities()
        self.get_logger().info("inactive: unsubscribed, publishers destroyed")
        return super().on_deactivate(state)

    def on_cleanup(self, state: LifecycleState) -> TransitionCallbackReturn:
        self._destroy_entities()
        self.online = None
        return TransitionCallbackReturn.SUCCESS

    def on_shutdown(self, state: LifecycleState) -> TransitionCallbackReturn:
        self._destroy_entities()
        self.online = None
        return TransitionCallbackReturn.SUCCESS

    def _destroy_entities(self) -> None:
        timer = getattr(self, "quarantine_timer", None)
        if timer is not None:
            self.destroy_timer(timer)
            self.quarantine_timer = None
        for e in self.entities:
            if e is None:
                continue
            if e is getattr(self, "sub", None):
                self.destroy_subscription(e)
            else:
                self.destroy_publisher(e)
        self.entities = []
        self.sub = None

    # ---- per message ---------------------------------------------------------------------------------
    def _on_observation(self, raw: bytes) -> None:
        if self.online is None:
            return
        try:
            results = self.online.feed(raw)
        except MessageError as exc:
            self.counts["bad"] += 1
            self._warn(f"bad observation dropped: {exc}")
            return
        except Exception as exc:  # a failure inside a method must not take the node down
            self._method_failed(exc)
            return
        self._publish(results)

    def _on_quarantine(self) -> None:
        if self.online is None or not self.online.held:
            return
        try:
            results = self.online.poll()
        except Exception as exc:  # a failure inside a method must not take the node down
            self._method_failed(exc)
            return
        self._publish(results)

    def _method_failed(self, exc: Exception) -> None:
        self.online.reset()
        self.get_logger().error(f"{self.method} failed on an observation ({exc!r}); restarting from the prior")

    def _publish(self, results) -> None:
        """Publish the estimates among ``results`` (OnlineEstimator.feed); count the others."""
        for res in results:
            if res.status == "held":
                continue  # counted once it is estimated or dropped
            if res.status != "estimated":
                self.counts["skipped"] += 1
                continue
            publish_result(res, self.pub_est, self.pub_cov, self.outputs)
            self.counts["estimates"] += 1

    def _warn(self, text: str) -> None:
        warn_throttled(self, self._last_log, "observation", text, self.p.log_throttle)


def main(args: list[str] | None = None) -> int:
    return run_node(LifecycleEstimatorNode, "lifecycle_estimator", args)


if __name__ == "__main__":
    sys.exit(main())
