"""The grasp planner: candidate grasps from each object's geometry (``candidates``), scored in
simulation with the rule-based closing, the lift and the pushes (``score``), the best per grasp type
stored in the library's grasp file (``plan``; read at run time by ``d3grasp.envs.grasp_file``)."""
