"""Fitted constants of the muscle families (families.py); data, not code.

Written by `python -m pma_sim.fit_families --write` (docs/simulated-rig.md);
do not edit by hand. Fit of each family's steady major loop to Table 1:

- narrow: RMSE 0.067 cm, max 0.176 cm over 22 points
- wide: RMSE 0.097 cm, max 0.259 cm over 22 points
- asymmetric: RMSE 0.092 cm, max 0.162 cm over 22 points
- creep: the narrow fit at the end of each hold (creep share 0.25, time constant 0.6 s)
"""

WIDE = {'rest_length_m': 0.3006,
 'dead_zone_pa': 51285.09,
 'warp_k_pa': 167308.1,
 'warp_n': 1.31044,
 'radii': [0.0, 0.02368421, 0.04736842, 0.07105263, 0.09473684, 0.1184211, 0.1421053,
           0.1657895, 0.1894737, 0.2131579, 0.2368421, 0.2605263, 0.2842105, 0.3078947,
           0.3315789, 0.3552632, 0.3789474, 0.4026316, 0.4263158, 0.45],
 'weights_m': [0.03319295, 0.01893052, 0.007445844, 0.001230271, 0.0, 0.0004186613,
               0.001336942, 0.001712155, 0.001248674, 0.0003400186, 0.0, 0.0, 0.0, 0.0,
               0.0, 2.129587e-11, 0.001293472, 0.003198543, 0.004734517, 0.005985699]}

ASYMMETRIC = {'rest_length_m': 0.3016428,
 'rising': {'stroke_m': 0.06038642,
            'mix': 0.2154661,
            'centre1_pa': 154489.1,
            'sd1_pa': 70875.57,
            'centre2_pa': 395237.7,
            'sd2_pa': 43282.9},
 'falling': {'stroke_m': 0.05503571,
             'mix': 0.6457831,
             'centre1_pa': 91820.27,
             'sd1_pa': 30000.0,
             'centre2_pa': 200176.0,
             'sd2_pa': 82311.42},
 'rising_scale_pa': 15000.0,
 'falling_scale_pa': 100000.0}

CREEP = {'share': 0.25, 'time_constant_s': 0.6}
