// Pausing a raw subscription's delivery while the bus runs (the coupler's second-writer check, issue
// 15.1): while stopped, the channel's messages wake no handler thread (LCM drops them on arrival).
#pragma once

#include <mutex>

#include "haptree/bus/bus.hpp"

namespace haptree::bus {

// Stops (on = false) or resumes sub's delivery: an LCM unsubscribe / subscribe; the Subscription and its
// counters stay. Any thread except a handler's; resuming allocates. A dispatch already under way on the
// handler thread may still deliver one message after a stop (LCM's C library frees the handler only
// when that dispatch returns; the Subscription outlives it). Serialised with Bus::subscribe and
// subscribe_raw by delivery_mutex() (bus.hpp).
void set_delivery(Bus& bus, RawSubscription& sub, bool on);

}  // namespace haptree::bus
