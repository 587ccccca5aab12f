"""The algorithms the device runs: the declaration of their memory (layout: state fields, parameters, flags, rendered
into the C header and the fallback), the float64 references that specify them (reference: the seed windows; fused:
the GPS-aided method) and their C kernel compiled on the host with cffi (hostkernel, hostfused) for equivalence
tests and benchmarks."""
