"""lcpr_common: the helpers every package of the project shares, importable without torch or ROS.

Progress bars (:mod:`.progress`), where ``../shared`` lives (:mod:`.shared_data`), the flat
float32 point files of the datasets (:mod:`.point_files`), the root of the project's own errors
(:mod:`.errors`) and how a command ends on them (:mod:`.cli`). ``lcpr_core``, ``msg_tools`` and
``citysim`` all import these; this package imports none of the project's others (the import
contracts in setup.cfg hold it to that), so the light packages stay light.
"""
