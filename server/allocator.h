// The malloc placedb-server runs on, chosen at build time (CMake PLACEDB_ALLOCATOR: glibc, the
// default, jemalloc or mimalloc), and its tuning: memory freed after a load goes back to the OS
// within seconds instead of staying in the allocator (issue 19; docs/service.md, "Memory budget",
// has the measurements that chose the default).
//
// - glibc: two arenas instead of 8 x cores, blocks of 1 MiB and more (messages, images) mmapped
//   so that freeing them unmaps them, and malloc_trim(0) every 5 s for the rest (glibc returns
//   little on its own).
// - jemalloc: linked into the executable, configured by the `malloc_conf` it defines
//   (background purging threads, freed pages returned after 1 s); MALLOC_CONF still overrides.
// - mimalloc: linked into the executable (it replaces malloc); freed pages decommitted.
//
// Only the executable links this (server/main.cc): tests and sanitizer builds keep the system
// allocator (ASan and TSan replace malloc themselves).
#pragma once

#include <string>

namespace placedb::server {

// Early in main(), before the server starts, after the signal mask is set (it may start a
// thread, which inherits the mask): applies the tuning above.
void TuneAllocator();

// "jemalloc 5.3.0-0-g54eaed1d8b56b1aa528be3bdd1877e59c56fa90c (...)", "mimalloc 209", "glibc 2.36
// (...)": for the startup log line.
std::string AllocatorDescription();

}  // namespace placedb::server
