/* What every public header of specklewfs shares: C linkage for C++ callers and the
 * symbols the shared library exports. The library is built with -fvisibility=hidden;
 * only what a public header declares between SWFS_BEGIN_DECLS and SWFS_END_DECLS is
 * exported from libspecklewfs.so, so internal helpers stay internal. */
#ifndef SWFS_DEFS_H
#define SWFS_DEFS_H

#if defined(__GNUC__)
#define SWFS_VISIBILITY_PUSH _Pragma("GCC visibility push(default)")
#define SWFS_VISIBILITY_POP _Pragma("GCC visibility pop")
#else
#define SWFS_VISIBILITY_PUSH
#define SWFS_VISIBILITY_POP
#endif

/* Complex numbers cross the API only by pointer (arrays, struct members), never by value.
 * In C they are C99 _Complex; a C++ caller sees std::complex, which has the same layout
 * (two consecutive values, real then imaginary), as does numpy's complex128. */
#ifdef __cplusplus
#include <complex>
typedef std::complex<double> swfs_complex;
typedef std::complex<float> swfs_complexf;
#else
#include <complex.h>
typedef double _Complex swfs_complex;
typedef float _Complex swfs_complexf;
#endif

#ifdef __cplusplus
#define SWFS_BEGIN_DECLS extern "C" { SWFS_VISIBILITY_PUSH
#define SWFS_END_DECLS SWFS_VISIBILITY_POP }
#else
#define SWFS_BEGIN_DECLS SWFS_VISIBILITY_PUSH
#define SWFS_END_DECLS SWFS_VISIBILITY_POP
#endif

#endif
