"""Host side of the trigger microcontroller: message table, packets, serial link, clock sync."""
