"""The nonparametric policy: dataset, state vectors, Lipschitz constants, bounds, the exact kd-tree index.

May import: nothing else of npp_ros (the bottom layer).
"""
