"""Reference methods that *produce* submissions (heavier dependencies: torch, diffusers, pycolmap).

`skyeyes_bench` never imports this package except through lazy "module:attr" strings.
"""
