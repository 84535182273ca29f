from plotmosaic.entry import main

main()
