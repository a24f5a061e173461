// All CPU kernels of gdiff.splat in one translation unit (what csrc/__init__.py compiles).
//
// The torch headers dominate the build: compiled apart, every file parses them again (one
// compiler process of several hundred MB each). One unit parses them once: less CPU time on
// the first run and a single compiler's memory. Each kernel stays in its own file (each also
// compiles on its own); their helpers share this unit's anonymous namespace, where same-named
// helpers differ in their parameters. The build hashes all the files, so editing any rebuilds.
#include "rasterize_cpu.cpp"
#include "project_cpu.cpp"
#include "sh_cpu.cpp"
#include "hexplane_cpu.cpp"
