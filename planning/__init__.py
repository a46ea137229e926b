"""Grasp planning from a depth image: sample 6-DOF antipodal grasps on the observed points,
reject those whose gripper hits the points or the table, score the rest with Fast-VGQ-CNN
and return the best distinct ones. numpy, scipy and onnxruntime only (no torch, no trimesh):
the service image can carry it.

Entry point: :func:`planning.policy.plan`.
"""
