"""Handlers shipped with elasticfog: Python services a fleet names as `handler: module:function`
(common.handlers), usable as they are and as worked examples of writing one.

- `perception.apriltag:detect`: AprilTag 36h11 tags and their 6-DoF poses (docs/services.md).
"""
