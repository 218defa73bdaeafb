"""The certificate: what is checked, the stopping rules, what is claimed and how it is worded, value conventions.

May import: npp_ros.policy.
"""
