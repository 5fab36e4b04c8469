"""Direct-to-indirect transfer (Hasan, Pellacini & Bala 2006; GPU Gems 3 ch. 9).

    v = v_d + F (I + M + M^2 + ... + M^(B-1)) g_d

v_d is the direct light on the view samples (the direct `Relighter`), g_d the light leaving the
gather samples after one reflection of each light (`gather_light`), F the final-gather matrix (view
samples x gathers) and M one diffuse bounce between gathers, both stored as 2-D Haar wavelet rows
with the top-k coefficients kept (`haar`, `sparse`); B is the baked bounce count.
"""
