// MIEM_CLONES: the vectorised kernels compiled for x86-64-v4 (AVX-512), AVX2 and the baseline,
// one picked at load time (GCC target clones on x86-64 Linux; elsewhere the plain function).
// Their loops keep each lane's arithmetic to itself, so every clone gives the same bits.
#pragma once

#if defined(__GNUC__) && !defined(__clang__) && defined(__x86_64__) && defined(__linux__)
#define MIEM_CLONES __attribute__((target_clones("arch=x86-64-v4", "avx2", "default")))
#else
#define MIEM_CLONES
#endif
