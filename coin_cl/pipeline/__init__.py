"""CoIn's stages, one module per paper stage, on a manifest-driven stage runner (`runner`).

The only package that joins the engine (`coin_cl.engine`, `coin_cl.gs`) and the 2D branch
(`coin_cl.diffusion`).
"""
