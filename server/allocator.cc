#include "server/allocator.h"

#include <chrono>
#include <thread>

#if defined(PLACEDB_ALLOCATOR_JEMALLOC)
#include <jemalloc/jemalloc.h>

// Read by jemalloc at its first allocation (MALLOC_CONF overrides it). Background threads purge
// without waiting for an allocation to do it; dirty pages (freed, still mapped) go back to the OS
// after 1 s, muzzy ones (lazily freed) at once: after a flood RSS returns to the baseline within
// seconds, and a steady load keeps its working set.
extern "C" {
const char* malloc_conf = "background_thread:true,dirty_decay_ms:1000,muzzy_decay_ms:0";
}
#elif defined(PLACEDB_ALLOCATOR_MIMALLOC)
#include <mimalloc.h>
#else
#include <gnu/libc-version.h>
#include <malloc.h>
#endif

namespace placedb::server {

void TuneAllocator() {
#if defined(PLACEDB_ALLOCATOR_GLIBC)
  // glibc keeps freed memory: up to 8 arenas per core, each trimmed only from its top. Two arenas
  // (the workers are few), frames' large buffers mmapped (returned on free), and a periodic trim
  // of every arena's free pages.
  mallopt(M_ARENA_MAX, 2);
  mallopt(M_MMAP_THRESHOLD, 1 << 20);
  mallopt(M_TRIM_THRESHOLD, 8 << 20);
  std::thread([] {
    while (true) {
      std::this_thread::sleep_for(std::chrono::seconds(5));
      malloc_trim(0);
    }
  }).detach();
#endif
}

std::string AllocatorDescription() {
#if defined(PLACEDB_ALLOCATOR_JEMALLOC)
  const char* version = "?";
  size_t size = sizeof version;
  mallctl("version", &version, &size, nullptr, 0);
  const char* conf = malloc_conf;
  return std::string("jemalloc ") + version + " (" + conf + ")";
#elif defined(PLACEDB_ALLOCATOR_MIMALLOC)
  return "mimalloc " + std::to_string(mi_version());
#else
  return std::string("glibc ") + gnu_get_libc_version() +
         " (2 arenas, mmap >= 1 MiB, malloc_trim every 5 s)";
#endif
}

}  // namespace placedb::server
