"""The built-in worlds, predictors, planners and values of overhang-framework.

They are an ordinary plugin, loaded through the ``overhang_framework`` entry-point
group exactly as a third-party plugin is.
"""

from overhang_framework.hookspecs import hookimpl


@hookimpl
def register_worlds(register):
    from overhang_builtins.world import OverhangWorld

    register("overhang", OverhangWorld)


@hookimpl
def register_predictors(register):
    from overhang_builtins.cnn import CNNPredictor
    from overhang_builtins.hand import HandPredictor
    from overhang_builtins.hybrid import HybridPredictor
    from overhang_builtins.simulation import IPEPredictor, VeridicalPredictor

    register("veridical", VeridicalPredictor)
    register("ipe", IPEPredictor)
    register("cnn", CNNPredictor)
    register("hybrid", HybridPredictor)
    register("hand", HandPredictor)


@hookimpl
def register_planners(register):
    from overhang_builtins.edge import EdgePlanner
    from overhang_builtins.lookahead import LookaheadPlanner
    from overhang_builtins.mcts import MCTSPlanner
    from overhang_builtins.myopic import MyopicPlanner
    from overhang_builtins.optimal import OptimalPlanner
    from overhang_builtins.policy import PolicyPlanner

    register("myopic", MyopicPlanner)
    register("lookahead", LookaheadPlanner)
    register("mcts", MCTSPlanner)
    register("optimal", OptimalPlanner)
    register("policy", PolicyPlanner)
    register("edge", EdgePlanner)


@hookimpl
def register_values(register):
    from overhang_builtins.values import OverhangValue, RolloutValue

    register("overhang", OverhangValue)
    register("rollout", RolloutValue)
