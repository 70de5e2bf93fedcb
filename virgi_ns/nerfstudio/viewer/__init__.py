"""VIRGi's panel in nerfstudio's viewer (:mod:`.panel`)."""
