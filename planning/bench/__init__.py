"""Planning benchmark: speed, and precision judged by datagen's oracle.

``python -m planning.bench timing``: p50 / p99 of :func:`planning.policy.plan` on a
300 x 300 rendered scene (256 candidates, encoder included), with the stages' medians.

``python -m planning.bench precision``: scenes of held-out test objects of the bundled
model's recipe (the ``object_id``s of examples/heldout_test_crops.npz, or of a crop
dataset's test split given as ``--heldout DIR``, index the recipe's objects), each on a
stable pose drawn by probability under a camera drawn from the recipe's ranges, rendered by
datagen. The planner sees only the depth image. Every
candidate it scored is judged by the oracle: robust Ferrari-Canny on the true mesh
(datagen.quality, the recipe's parameters) > its threshold, or with ``--oracle physics``
(the default for a model trained on the physics label) the recipe's noisy pybullet trials
(datagen.physics) succeeding more often than the label's threshold, for the top 5 and a
random sample of the candidates; and no collision of the swept gripper with the true mesh or
the table (datagen.collision) at the known camera pose. Reported: precision@1 and @5 of the plan (top-k after NMS), of a random
collision-free candidate of the same sampler (its expectation: the positive share of the
candidates), and of the pose-only baseline's ranking of the same candidates when its model
file exists (``--baseline FILE`` or ``baseline_mlp.npz`` in the model folder).

``python -m planning.bench ceiling``: the same scenes, judged on datagen's own grasps on the
true mesh instead of the planner's: how often the best of a scene's true-mesh grasps by one
judging of the physics oracle passes a second one (what no ranking of any pool can beat by much).

Needs the datagen extra (trimesh, python-fcl, embree); the planner itself does not.
"""
