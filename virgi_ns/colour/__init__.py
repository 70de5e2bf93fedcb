"""How a Gaussian gets its colour: VIRGi's colour field (:mod:`.field`: hash-grid features, a
diffuse and a specular MLP) and 3DGS's spherical harmonics (:mod:`.sh`), which splat files carry
and exports are baked into. Nothing here renders; positions and directions go in, colours come out.
"""
