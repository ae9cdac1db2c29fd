"""Training supervision: the targets built from a batch in the loader (anchor assignment, depth
and class of the lidar seen by each camera feature cell) and the losses over the model's outputs.
"""
