"""gravcal.io: recordings and their formats, the measured data sets, the offline reading pass and studies."""
