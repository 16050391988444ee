"""Host side of the trigger microcontroller: message table, framing, serial link, clock sync."""
