"""lcpr_offline: lcpr_core fed from recordings and the synthetic city, for the offline jobs.

Above both lcpr_core and the data packages (msg_tools reads rosbag2, citysim renders drives), so
that lcpr_core imports neither: the evaluation of a bag (:mod:`.lcpr_evaluate`, the engine of
``lcpr_eval``), LCPR's training cache and command (:mod:`.lcpr_cache`, :mod:`.lcpr_train`:
``lcpr_train``), the int8 calibration on a synthetic city (:mod:`.lcpr_quantize`: ``lcpr_quantize``)
and VSeq2PC's feature cache of a bag (:mod:`.vseq2pc_cache`: ``vseq2pc_cache``). No DDS, no rclpy.

What the scripts under benchmarks/ share lives here too: the recipes' steps (:mod:`.lcpr_recipe`), the
robustness conditions (:mod:`.lcpr_robustness`), the int8 studies' bench (:mod:`.lcpr_int8_study`) and
the verifier's pairs with a known answer (:mod:`.verification_pairs`).
"""
